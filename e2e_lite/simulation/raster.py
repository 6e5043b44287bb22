"""The rasteriser's parts, shared by the front camera and the top-down view: the palette and the
painted sizes, OpenCV's fixed-point pixels, the near-plane clip, the fills of a camera frame
(:func:`paint`), the trajectory overlay on a camera frame (:func:`draw_trajectory`), and PNG
output.

All colours are RGB. Pixel coordinates are floats with pixel centres at integers; OpenCV draws
them with ``SHIFT`` fractional bits (:func:`to_fixed`), so edges land between pixels and are
anti-aliased rather than snapped.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from ..artifacts import atomic_write, show_in_notebook


class Projection(Protocol):
    """What the trajectory overlay needs of a camera (:class:`~e2e_lite.simulation.camera.Camera`):
    its settings and the projection of car-frame points to pixels."""

    cfg: Any

    def project_car(self, pts_car: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


SHIFT = 4  # sub-pixel bits for OpenCV fills
SCALE = float(1 << SHIFT)


def to_fixed(px: np.ndarray) -> np.ndarray:
    """Pixel coordinates to OpenCV's fixed point with ``SHIFT`` fractional bits (C-ordered int32)."""
    return np.round(px * SCALE).astype(np.int32, order="C")


# colours (RGB)
SKY = (160, 196, 232)
GRASS = (92, 138, 70)
SHOULDER = (120, 120, 118)
ROAD = (78, 78, 84)
MARKING = (236, 236, 236)
RAIL = (190, 190, 196)
CAR_COLOURS = ((200, 40, 40), (40, 90, 200), (230, 190, 40), (235, 235, 235), (60, 60, 60))
EGO_COLOUR = (30, 110, 255)
FACE_SHADE = {"back": 0.72, "front": 0.72, "left": 0.55, "right": 0.55, "top": 1.0}

RAIL_HEIGHT_M = 0.8
MARK_WIDTH_M = 0.15
DASH_M, DASH_PERIOD_M = 3.0, 12.0


def strip_line(lines: np.ndarray, tops: np.ndarray, b: int, i: int) -> np.ndarray:
    """Line ``i`` of frame ``b`` among the 6 ground lines followed by the 2 rail tops."""
    return lines[b, i] if i < 6 else tops[b, i - 6]


# dash corners: along-road offsets (from the dash start) and lateral offsets (from the line)
DASH_S = np.array([0.0, DASH_M, DASH_M, 0.0])
DASH_D = np.array([-1.0, -1.0, 1.0, 1.0]) * (MARK_WIDTH_M / 2)
# the ground strips as (line, line) pairs of [6 ground lines, 2 rail tops]:
# shoulder, road, left edge line, right edge line, right rail, left rail
STRIPS = ((0, 1), (2, 3), (3, 4), (5, 2), (0, 6), (1, 7))
STRIP_A = np.array([a for a, _ in STRIPS])
STRIP_B = np.array([b for _, b in STRIPS])
# faces of ParkedCars.box_corners_3d, in the order of the visibility tests: back, front, right, left, top
FACES = ([0, 3, 7, 4], [1, 5, 6, 2], [0, 4, 5, 1], [3, 2, 6, 7], [4, 5, 6, 7])
FACE_INDEX = np.array(FACES)
FACE_COLOURS = tuple(
    tuple(
        tuple(int(ch * FACE_SHADE[f]) for ch in base)
        for f in ("back", "front", "right", "left", "top")
    )
    for base in CAR_COLOURS
)


def clip_strips(lines: np.ndarray, near: float) -> tuple[np.ndarray, np.ndarray]:
    """The ground strips of B frames, clipped at the near plane; (B, 6, 2n, 3) and a (B,) mask.

    ``lines`` is (B, 8, n, 3): per frame, 8 polylines sampled at the same arc lengths. A strip is
    ``[line a forward, line b backward]``. When a line's samples, once in front of the near plane,
    stay in front (the car faces roughly along the road), every sample behind it is replaced by
    the line's crossing point. The strip then keeps the same outline as a Sutherland-Hodgman clip,
    with repeated vertices that fill nothing. Frames where that does not hold are flagged
    ``False`` (the caller clips them polygon by polygon); so are frames where a line is wholly
    behind the camera.
    """
    z = lines[..., 2]  # (B, 8, n)
    front = z >= near
    once = np.all(front[..., 1:] >= front[..., :-1], axis=(1, 2))  # never back behind
    seen = np.all(front[..., -1], axis=1)  # every line reaches in front
    first = np.argmax(front, axis=-1)  # (B, 8)
    prev = np.maximum(first - 1, 0)
    za = np.take_along_axis(z, prev[..., None], -1)[..., 0]
    zb = np.take_along_axis(z, first[..., None], -1)[..., 0]
    pa = np.take_along_axis(lines, prev[..., None, None], 2)[:, :, 0]  # (B, 8, 3)
    pb = np.take_along_axis(lines, first[..., None, None], 2)[:, :, 0]
    frac = np.where(first > 0, (near - za) / np.where(zb > za, zb - za, 1.0), 0.0)
    cut = pa + frac[..., None] * (pb - pa)
    clipped = np.where(front[..., None], lines, cut[:, :, None, :])
    strips = np.concatenate([clipped[:, STRIP_A], clipped[:, STRIP_B, ::-1]], axis=2)
    strips[..., 2] = np.maximum(strips[..., 2], near)  # the crossing points sit on the plane
    return strips, once & seen


def clip_near(poly: np.ndarray, near: float) -> np.ndarray | None:
    """Sutherland-Hodgman clip of a camera-frame polygon ``(N, 3)`` to the half-space ``z >= near``.

    Returns the clipped polygon, or ``None`` when nothing is in front. For each edge ``i -> i+1``:
    keep vertex ``i`` if it is inside, and add the edge's crossing point if the edge crosses.
    (Plain Python: the polygons that need it are few and small, where numpy's call overhead
    would dominate.)
    """
    z = poly[:, 2]
    if z.min() >= near:
        return poly
    if z.max() < near:
        return None
    pts = poly.tolist()
    out = []
    for (xa, ya, za), (xb, yb, zb) in zip(pts, pts[1:] + pts[:1]):
        if za >= near:
            out.append((xa, ya, za))
        if (za >= near) != (zb >= near):
            f = (near - za) / (zb - za)
            out.append((xa + f * (xb - xa), ya + f * (yb - ya), near))
    return np.array(out) if len(out) >= 3 else None


def paint(
    img: np.ndarray,
    bands: Sequence[np.ndarray | None],
    road_colour: tuple[int, int, int],
    marks: list[np.ndarray],
    car_faces: list[tuple[np.ndarray, tuple[int, int, int]]],
    brightness: float = 1.0,
) -> np.ndarray:
    """Fill one camera frame far to near (the painter's algorithm) over its background, in place:
    the shoulder and the road (``bands[0]``, ``bands[1]``), the markings, the two rails'
    walls (``bands[4:6]``), the cars' faces (farthest first), then the brightness gain. Polygons
    are fixed-point pixels (:func:`to_fixed`); a None band is wholly behind the camera."""
    for poly, colour in ((bands[0], SHOULDER), (bands[1], road_colour)):
        if poly is not None:
            cv2.fillPoly(img, [poly], colour, cv2.LINE_AA, SHIFT)
    if marks:
        cv2.fillPoly(img, marks, MARKING, cv2.LINE_AA, SHIFT)
    walls = [p for p in bands[4:6] if p is not None]
    if walls:
        cv2.fillPoly(img, walls, RAIL, cv2.LINE_AA, SHIFT)
    for pts, colour in car_faces:
        cv2.fillConvexPoly(img, pts, colour, cv2.LINE_AA, SHIFT)
    if brightness != 1.0:
        cv2.convertScaleAbs(img, dst=img, alpha=brightness)
    return img


def draw_trajectory(
    image: np.ndarray,
    points_car: np.ndarray,
    camera: Projection,
    colour: tuple[int, int, int] = (255, 40, 40),
    radius_px: int | None = None,
    thickness_px: int | None = None,
    label: str | None = None,
) -> np.ndarray:
    """Draw a car-frame trajectory ``(K, 2)`` (x forward, y left; metres) on a camera image.

    Points are projected on the road surface; points behind the near plane are skipped. The
    polyline starts at the road point below the camera's near plane. Draws in place; returns it.
    """
    pts = np.asarray(points_car, dtype=np.float64).reshape(-1, 2)
    start = np.array([[camera.cfg.forward_offset_m + camera.cfg.near_m * 4, 0.0]])
    ground = np.concatenate([np.r_[start, pts], np.zeros((len(pts) + 1, 1))], axis=1)
    px, front = camera.project_car(ground)
    scale = max(1, round(image.shape[1] / 200))
    radius = radius_px if radius_px is not None else 1 + scale
    thick = thickness_px if thickness_px is not None else scale
    fixed = to_fixed(px[front])
    if len(fixed) >= 2:
        cv2.polylines(image, [fixed], False, colour, thick, cv2.LINE_AA, SHIFT)
    for p in fixed[1:] if front[0] else fixed:
        cv2.circle(
            image, (int(p[0]), int(p[1])), radius * int(SCALE), colour, -1, cv2.LINE_AA, SHIFT
        )
    if label and len(fixed):
        tip = fixed[-1] / SCALE
        cv2.putText(
            image,
            label,
            (int(tip[0]) + 3, int(tip[1])),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.3 * scale,
            colour,
            1,
            cv2.LINE_AA,
        )
    return image


def tile(images: Sequence[np.ndarray], columns: int) -> np.ndarray:
    """Images of one size ``(H, W, 3)`` laid out ``columns`` to a row, left to right and top to
    bottom, the last row filled with black: one ``(rows x H, columns x W, 3)`` image."""
    if not images:
        raise ValueError("tile needs at least one image")
    cells = list(images) + [np.zeros_like(images[0])] * (-len(images) % columns)
    rows = [np.concatenate(cells[k : k + columns], axis=1) for k in range(0, len(cells), columns)]
    return np.concatenate(rows, axis=0)


def save_image(path: Path | str, rgb: np.ndarray) -> Path:
    """Write an RGB image as PNG (OpenCV wants BGR), atomically; shown inline in a notebook.
    Returns the path."""
    path = Path(path)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise OSError(f"could not encode {path}")
    with atomic_write(path) as f:
        f.write(buf.tobytes())
    show_in_notebook(path)
    return path
