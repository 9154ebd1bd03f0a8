"""Procedural textures for the twin's objects (RGB uint8 images drawn with numpy and OpenCV).

Images follow the usual UV convention: column = u * width, row 0 = the top of the image = v 1.
Cylindrical labels have u going once around the object and v going up its side. ``rng`` is None for
the canonical look (clock at 10:10, a fixed photo); a generator varies details but never geometry.
"""

from __future__ import annotations

import cv2
import numpy as np

RGB = tuple[int, int, int]


def _blank(height: int, width: int, colour: RGB) -> np.ndarray:
    image = np.empty((height, width, 3), np.uint8)
    image[:] = colour
    return image


def _text(image: np.ndarray, text: str, centre: tuple[int, int], scale: float, colour: RGB,
          thickness: int) -> None:
    font = cv2.FONT_HERSHEY_DUPLEX
    (w, h), _ = cv2.getTextSize(text, font, scale, thickness)
    origin = (int(centre[0] - w / 2), int(centre[1] + h / 2))
    cv2.putText(image, text, origin, font, scale, colour, thickness, cv2.LINE_AA)


def can_label(rng: np.random.Generator | None = None) -> np.ndarray:
    """The energy-drink can's wrap: blue and silver checks, a yellow sun with a red emblem, twice."""
    h, w = 512, 1024
    image = _blank(h, w, (196, 200, 206))
    cell = 32
    rows, cols = np.mgrid[0:h, 0:w]
    checks = ((rows // cell + cols // cell) % 2 == 0) & ((rows < 150) | (rows > 400))
    image[checks] = (20, 45, 120)
    image[rows > 470] = (20, 45, 120)
    shift = 0 if rng is None else int(rng.integers(0, w))
    for k in range(2):
        cx = (w // 4 + k * w // 2 + shift) % w
        cv2.circle(image, (cx, 250), 62, (250, 200, 20), -1, cv2.LINE_AA)
        for dx in (-70, 70):
            cv2.ellipse(image, (cx + dx, 262), (56, 30), 0, 0, 360, (200, 20, 45), -1, cv2.LINE_AA)
        _text(image, "RED BULL", (cx, 355), 1.4, (200, 20, 45), 3)
    return image


def ketchup_label(rng: np.random.Generator | None = None) -> np.ndarray:
    """A red bottle with a white keystone label on its front and back faces."""
    h, w = 512, 1024
    image = _blank(h, w, (176, 18, 22))
    for k, cx in enumerate((w // 4, 3 * w // 4)):
        top, bottom, half_top, half_bottom = 120, 360, 120, 150
        poly = np.array([[cx - half_top, top], [cx + half_top, top], [cx + half_bottom, bottom],
                         [cx - half_bottom, bottom]], np.int32)
        cv2.fillPoly(image, [poly], (245, 240, 228), cv2.LINE_AA)
        _text(image, "KETCHUP", (cx, 230), 1.3, (176, 18, 22), 3)
        cv2.circle(image, (cx, 300), 26, (200, 30, 25), -1, cv2.LINE_AA)
        cv2.ellipse(image, (cx, 272), (16, 6), 0, 0, 360, (40, 140, 40), -1, cv2.LINE_AA)
        if k == 1:
            _text(image, "57", (cx, 165), 0.9, (40, 120, 40), 2)
    return image


def mug_glaze(rng: np.random.Generator | None = None) -> np.ndarray:
    """A glazed mug: a solid colour with a white band and a short word on one side."""
    palette = [(28, 60, 130), (150, 30, 40), (40, 110, 80), (210, 150, 40)]
    colour = palette[0] if rng is None else palette[int(rng.integers(0, len(palette)))]
    h, w = 256, 1024
    image = _blank(h, w, colour)
    image[150:175] = (245, 245, 240)
    _text(image, "DARP", (w // 2, 95), 1.6, (245, 245, 240), 3)
    return image


def cup_print(rng: np.random.Generator | None = None) -> np.ndarray:
    """A paper coffee cup: white with a coloured sleeve band and dots."""
    band = (120, 72, 40) if rng is None else tuple(int(c) for c in rng.integers(40, 200, 3))
    h, w = 512, 1024
    image = _blank(h, w, (246, 244, 238))
    image[190:330] = band
    for k in range(16):
        cx = int((k + 0.5) * w / 16)
        cv2.circle(image, (cx, 260), 14, (246, 244, 238), -1, cv2.LINE_AA)
    return image


def clock_face(rng: np.random.Generator | None = None) -> np.ndarray:
    """A square image of a clock dial: 60 ticks, 12 hour marks, numerals and two hands."""
    n = 512
    c = n // 2
    image = _blank(n, n, (200, 200, 200))
    cv2.circle(image, (c, c), c - 1, (248, 246, 238), -1, cv2.LINE_AA)
    for k in range(60):
        a = 2 * np.pi * k / 60
        r0 = 0.80 if k % 5 == 0 else 0.88
        p0 = (int(c + r0 * c * np.sin(a)), int(c - r0 * c * np.cos(a)))
        p1 = (int(c + 0.95 * c * np.sin(a)), int(c - 0.95 * c * np.cos(a)))
        cv2.line(image, p0, p1, (20, 20, 20), 7 if k % 5 == 0 else 2, cv2.LINE_AA)
    for hour, a in ((12, 0.0), (3, 0.5 * np.pi), (6, np.pi), (9, 1.5 * np.pi)):
        _text(image, str(hour), (int(c + 0.66 * c * np.sin(a)), int(c - 0.66 * c * np.cos(a))), 1.6,
              (20, 20, 20), 3)
    minutes = 10 * 60 + 10 if rng is None else int(rng.integers(0, 12 * 60))
    for frac, length, width in ((minutes / 720.0, 0.5, 12), ((minutes % 60) / 60.0, 0.78, 7)):
        a = 2 * np.pi * frac
        tip = (int(c + length * c * np.sin(a)), int(c - length * c * np.cos(a)))
        cv2.line(image, (c, c), tip, (15, 15, 15), width, cv2.LINE_AA)
    cv2.circle(image, (c, c), 12, (170, 20, 20), -1, cv2.LINE_AA)
    return image


def frame_photo(rng: np.random.Generator | None = None) -> np.ndarray:
    """A landscape 'photo': sky gradient, sun, two mountain ridges and a lake."""
    h, w = 448, 512
    rows = np.linspace(0.0, 1.0, h)[:, None, None]
    shade: np.ndarray = ((1 - rows) * np.array([90, 150, 230]) + rows * np.array([200, 225, 245])) * np.ones((1, w, 1))
    image = shade.astype(np.uint8)
    gen = rng if rng is not None else np.random.default_rng(7)
    sun = (int(gen.integers(60, w - 60)), int(gen.integers(50, 140)))
    cv2.circle(image, sun, 34, (255, 220, 90), -1, cv2.LINE_AA)
    x = np.arange(w)
    for base, amp, colour in ((250, 70, (90, 110, 140)), (300, 45, (50, 100, 60))):
        phase = gen.uniform(0, 2 * np.pi, 3)
        ridge = base - amp * (0.6 * np.sin(x / 53 + phase[0]) + 0.3 * np.sin(x / 21 + phase[1])
                              + 0.1 * np.sin(x / 7 + phase[2]))
        poly = np.vstack([np.column_stack([x, ridge]), [[w - 1, h - 1], [0, h - 1]]]).astype(np.int32)
        cv2.fillPoly(image, [poly], colour, cv2.LINE_AA)
    image[340:] = (60, 110, 170)
    return image


def marble(rng: np.random.Generator | None = None) -> np.ndarray:
    """Blue-green swirled glass/resin, for the paperweight dome."""
    gen = rng if rng is not None else np.random.default_rng(3)
    h, w = 256, 512
    v, u = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    phase = gen.uniform(0, 2 * np.pi, 3)
    swirl = np.sin(2 * np.pi * (3 * u + 2 * v) + 2.5 * np.sin(2 * np.pi * (2 * u) + phase[0])
                   + 1.5 * np.sin(2 * np.pi * 5 * v + phase[1]))
    t = (0.5 + 0.5 * swirl)[..., None]
    image: np.ndarray = (1 - t) * np.array([20, 70, 120]) + t * np.array([120, 200, 200])
    return image.astype(np.uint8)


def knurl() -> np.ndarray:
    """Cross-hatched chrome for the dumbbell's grip."""
    h, w = 256, 512
    rows, cols = np.mgrid[0:h, 0:w]
    lines = ((rows + cols) % 16 < 3) | ((rows - cols) % 16 < 3)
    image = _blank(h, w, (190, 192, 196))
    image[lines] = (120, 122, 128)
    image[:40] = image[-40:] = (205, 207, 210)
    return image


def mean_rgba(image: np.ndarray) -> tuple[float, float, float, float]:
    """The image's mean colour as an rgba tuple in [0, 1] (a part's colour when textures are off)."""
    rgb = image.reshape(-1, 3).mean(axis=0) / 255.0
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0)
