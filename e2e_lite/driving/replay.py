"""Replays of closed-loop driving: a 3D meshcat scene as one standalone HTML file, and a GIF of
the camera view with the prediction drawn on it (chapter 10).

A replay is one car driving one stretch of a track (:func:`record`), the way the
evaluator drives it, stopping at the first collision. :func:`export_html` draws it with meshcat's
geometry and animation objects, but **without meshcat's server**: ``meshcat.Visualizer()`` starts
a ZMQ/web server process (see ``../shared/API_NOTES.md``); here the visualizer writes into a
:class:`RecordingWindow` that only keeps the encoded commands, and the page replays them into
meshcat's viewer script, which is inlined. The file opens from disk in any browser, offline.

What the scene shows: the road (surface, edge lines, dashed dividers, guard rails), the parked
cars, the ego car, and the car's declared intent at each decision: the 5 trajectory points it
proposed (for a GMM, every mode in its own colour, each point's size growing with the mode's
weight; the followed mode is the largest), drawn in the world where the car meant to be 0.3 to
1.5 s later. The viewer's camera follows the car from behind (the scene moves, see
:func:`build_scene`).
"""

from __future__ import annotations

import base64
import html
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import umsgpack
from PIL import Image

with warnings.catch_warnings():  # meshcat 0.3 imports a deprecated pyzmq module for its server
    warnings.simplefilter("ignore", DeprecationWarning)
    import meshcat
    import meshcat.geometry as g
    import meshcat.transformations as tf
    from meshcat.animation import Animation

from ..artifacts import atomic_write
from ..simulation.camera import Camera, CameraConfig
from ..simulation.geometry import Track
from ..simulation.policy import Actuation, Observation, Policy
from ..simulation.raster import CAR_COLOURS, DASH_M, DASH_PERIOD_M, RAIL_HEIGHT_M
from ..simulation.raster import draw_trajectory as draw_on_frame
from ..simulation.vehicle import VehicleParams
from ..simulation.world import ParkedCars, World, WorldConfig
from .rollout import drive

MODE_COLOURS = ((40, 110, 230), (240, 140, 30), (60, 170, 80), (170, 60, 170))
CAR_HEIGHT_M = 1.5


@dataclass
class Episode:
    """One recorded drive.

    Attributes:
        name: the driver's name.
        track, cars: the scene.
        states: ``(T + 1, 5)`` ego states at every decision (x, y, heading, speed, steer).
        modes: ``(T, K, 5, 2)`` proposed trajectories in the car frame [m] (K = 1 for a single
            trajectory), or None for drivers that propose none.
        weights: ``(T, K)`` the modes' weights (ones for a single trajectory).
        frames: camera views (RGB uint8) with the proposal drawn on them, one per decision.
        contact: ``"car"``, ``"rail"`` or None: how the drive ended.
        period_s: time between decisions [s].
        vehicle: the driven car (its body is drawn around the rear axle the states give).
    """

    name: str
    track: Track
    cars: ParkedCars
    states: np.ndarray
    modes: np.ndarray | None
    weights: np.ndarray | None
    frames: list[np.ndarray] = field(default_factory=list)
    contact: str | None = None
    period_s: float = 0.1
    vehicle: VehicleParams = field(default_factory=VehicleParams)

    @property
    def seconds(self) -> float:
        """Length of the drive [s]."""
        return (len(self.states) - 1) * self.period_s


def _proposal(policy: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """The policy's latest proposal for car 0: ``(modes (K, 5, 2), weights (K,))``."""
    last = getattr(policy, "last", None) or {}
    if "modes" in last:
        return np.asarray(last["modes"][0]), np.asarray(last["weights"][0])
    if "points" in last:
        return np.asarray(last["points"][0])[None], np.ones(1)
    return None


def record(
    policy: Policy,
    world: World,
    world_cfg: WorldConfig,
    name: str,
    s_m: float,
    lane: int,
    seconds: float = 30.0,
    speed_mps: float = 20.0,
    frames: bool = True,
) -> Episode:
    """Drive ``policy`` alone on ``world`` from arc length ``s_m`` in ``lane`` for ``seconds``
    (or until the first collision) and keep what a replay needs.

    Args:
        frames: also keep a 240 x 640 view per decision with the proposal drawn on it (for
            :func:`export_gif`).
    """
    view = Camera(CameraConfig.human())
    modes: list[np.ndarray] = []
    weights: list[np.ndarray] = []
    pictures: list[np.ndarray] = []

    def on_decision(obs: Observation, act: Actuation) -> None:
        prop = _proposal(policy)
        if prop is not None:
            modes.append(prop[0])
            weights.append(prop[1])
        if frames:
            img = view.render(world.track, world.cars, tuple(obs.state[0, :3]), float(obs.s[0]))
            if prop is not None:
                order = np.argsort(prop[1])  # the followed (heaviest) mode drawn last, on top
                for k in order:
                    draw_on_frame(
                        img,
                        prop[0][k],
                        view,
                        MODE_COLOURS[k % len(MODE_COLOURS)],
                        label=f"{prop[1][k]:.2f}" if len(prop[1]) > 1 else None,
                    )
            pictures.append(img)

    d = float(world.track.lane_center(lane))
    states, contacts = drive(
        policy, world, world_cfg, s_m, d, speed_mps, seconds, on_decision=on_decision
    )
    kind = None
    if contacts:
        kind = "car" if any(k == "car" for k, _ in contacts) else "rail"
    return Episode(
        name=name,
        track=world.track,
        cars=world.cars,
        states=states,
        modes=np.array(modes) if modes else None,
        weights=np.array(weights) if weights else None,
        frames=pictures,
        contact=kind,
        period_s=world_cfg.sim.policy_period_s,
        vehicle=world_cfg.vehicle,
    )


class RecordingWindow:
    """A stand-in for meshcat's server connection: keeps every command, encoded as meshcat's
    viewer expects it (msgpack), in order. No process, no socket."""

    def __init__(self) -> None:
        self.commands: list[bytes] = []

    def send(self, command: Any) -> None:
        """Keep one command (called by ``meshcat.Visualizer``)."""
        self.commands.append(umsgpack.packb(command.lower()))


CHASE_CAMERA_M = [-18.0, 9.0, 0.0]  # behind, up, side in the camera's y-up frame [m]


def _hex(rgb: tuple[int, int, int]) -> int:
    return (rgb[0] << 16) | (rgb[1] << 8) | rgb[2]


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    m = tf.rotation_matrix(yaw, [0.0, 0.0, 1.0])
    m[:3, 3] = (x, y, z)
    return m.astype(np.float64)


def _line(points_xy: np.ndarray, z: float) -> np.ndarray:
    """(N, 2) -> (3, N) float32 vertices at height z."""
    pts = np.asarray(points_xy, dtype=np.float32)
    return np.vstack([pts.T, np.full(len(pts), z, dtype=np.float32)])


def build_scene(ep: Episode, margin_m: float = 40.0, ahead_m: float = 120.0) -> RecordingWindow:
    """The episode as meshcat commands: the stretch of road it drove (from ``margin_m`` behind its
    first position to ``ahead_m`` past its last), the parked cars there, the ego's animation and
    its proposals' animation."""
    window = RecordingWindow()
    vis = meshcat.Visualizer(window=window)
    track = ep.track
    s_drive = np.array(track.to_frenet(ep.states[:, 0], ep.states[:, 1])[0], dtype=float)
    s_lo = max(0.0, float(s_drive.min()) - margin_m)
    s_hi = min(track.length, float(s_drive.max()) + ahead_m)
    _draw_road(vis, track, s_lo, s_hi)
    _draw_parked(vis, ep.cars, s_lo, s_hi)
    _draw_ego_and_plans(vis, ep)
    _animate(vis, ep)
    return window


def _draw_road(vis: meshcat.Visualizer, track: Track, s_lo: float, s_hi: float) -> None:
    """The road's surface, edge lines, dashed dividers and guard rails from ``s_lo`` to ``s_hi``."""
    s = np.arange(s_lo, s_hi, 2.0)
    # road surface: a triangle strip between the two edges
    left = track.position(s, track.half_width)
    right = track.position(s, -track.half_width)
    verts = np.concatenate([left, right]).astype(np.float32)
    verts = np.hstack([verts, np.full((len(verts), 1), -0.02, dtype=np.float32)])
    n = len(s)
    k = np.arange(n - 1)
    faces = np.concatenate([np.stack([k, k + 1, n + k], 1), np.stack([k + 1, n + k + 1, n + k], 1)])
    vis["road/surface"].set_object(
        g.TriangularMeshGeometry(verts, faces.astype(np.uint32)),
        g.MeshLambertMaterial(color=0x55595E),
    )
    white = g.LineBasicMaterial(color=0xF2F2F2, linewidth=2)
    for name, d in (
        ("edge_left", track.half_width - 0.15),
        ("edge_right", -track.half_width + 0.15),
    ):
        vis[f"road/{name}"].set_object(
            g.Line(g.PointsGeometry(_line(track.position(s, d), 0.01)), white)
        )
    # dashed dividers: DASH_M painted out of every DASH_PERIOD_M
    starts = np.arange(np.ceil(s_lo / DASH_PERIOD_M) * DASH_PERIOD_M, s_hi - DASH_M, DASH_PERIOD_M)
    for lane in range(1, track.n_lanes):
        d = float(track.lane_center(lane)) - track.lane_width / 2
        ends = np.stack([track.position(starts, d), track.position(starts + DASH_M, d)], 1)
        vis[f"road/divider_{lane}"].set_object(
            g.LineSegments(g.PointsGeometry(_line(ends.reshape(-1, 2), 0.01)), white)
        )
    rail = g.LineBasicMaterial(color=0xB8BCC2, linewidth=3)
    for name, d in (("rail_left", track.rail_d), ("rail_right", -track.rail_d)):
        xy = track.position(s, d)
        for z, part in ((RAIL_HEIGHT_M, "top"), (RAIL_HEIGHT_M * 0.6, "mid")):
            vis[f"road/{name}_{part}"].set_object(g.Line(g.PointsGeometry(_line(xy, z)), rail))


def _draw_parked(vis: meshcat.Visualizer, cars: ParkedCars, s_lo: float, s_hi: float) -> None:
    """The parked cars between arc lengths ``s_lo`` and ``s_hi``, as coloured boxes."""
    box = g.Box([cars.length_m, cars.width_m, CAR_HEIGHT_M])
    for i in range(*_slice(cars, s_lo, s_hi)):
        colour = _hex(CAR_COLOURS[i % len(CAR_COLOURS)])
        node = vis[f"parked/car_{i}"]
        node.set_object(box, g.MeshLambertMaterial(color=colour))
        node.set_transform(
            _pose(float(cars.x[i]), float(cars.y[i]), CAR_HEIGHT_M / 2, float(cars.heading[i]))
        )


def _draw_ego_and_plans(vis: meshcat.Visualizer, ep: Episode) -> None:
    """The ego's box and a sphere per proposed point (5 per mode), and the chase camera.

    meshcat's orbit controls aim the camera at the *world* origin whatever frame the camera sits
    in, so moving the camera with the car left it looking back at the origin. Instead the scene
    moves (:func:`_animate`): every object lives under /meshcat, whose transform each frame is the
    inverse of the car's pose, so the car stays at the origin facing +x, and the camera sits 18 m
    behind it and 9 m up (the camera's frame is y-up), looking at it; dragging orbits around
    the car."""
    veh = ep.vehicle
    vis["ego"].set_object(
        g.Box([veh.length_m, veh.width_m, CAR_HEIGHT_M]), g.MeshLambertMaterial(color=0xE8322C)
    )
    for m in range(0 if ep.modes is None else ep.modes.shape[1]):
        mat = g.MeshLambertMaterial(color=_hex(MODE_COLOURS[m % len(MODE_COLOURS)]))
        for p in range(5):
            vis[f"plan/mode_{m}/p{p}"].set_object(g.Sphere(0.45), mat)
    vis["/Cameras/default/rotated/<object>"].set_property("position", CHASE_CAMERA_M)
    vis["/Grid"].set_property("visible", False)  # the default grid sits at the world's origin
    vis["/Axes"].set_property("visible", False)


def _animate(vis: meshcat.Visualizer, ep: Episode) -> None:
    """One animation frame per decision: the ego's pose, the scene moved so the car stays at
    the origin, and each proposed point placed and scaled by its mode's weight."""
    veh = ep.vehicle
    n_modes = 0 if ep.modes is None else ep.modes.shape[1]
    anim = Animation(default_framerate=round(1.0 / ep.period_s))
    rear_to_centre = veh.rear_to_centre_m
    for f, (x, y, h) in enumerate(ep.states[:, :3]):
        with anim.at_frame(vis, f) as frame:
            cx, cy = x + rear_to_centre * np.cos(h), y + rear_to_centre * np.sin(h)
            frame["ego"].set_transform(_pose(cx, cy, CAR_HEIGHT_M / 2, h))
            frame["/meshcat"].set_transform(np.linalg.inv(_pose(cx, cy, 0.0, h)))
            if ep.modes is None or f >= len(ep.modes):
                continue
            c, si = np.cos(h), np.sin(h)
            for m in range(n_modes):
                w = float(ep.weights[f, m])
                for p, (px, py) in enumerate(ep.modes[f, m]):
                    wx, wy = x + c * px - si * py, y + si * px + c * py
                    node = frame[f"plan/mode_{m}/p{p}"]
                    node.set_transform(_pose(wx, wy, 0.45, 0.0))
                    size = 0.25 + 0.75 * w  # an animated transform keeps no scale
                    node.set_property("scale", "vector3", [size, size, size])
    vis.set_animation(anim, play=True, repetitions=1)


def _slice(cars: ParkedCars, s_lo: float, s_hi: float) -> tuple[int, int]:
    if len(cars) == 0:
        return 0, 0
    sl = cars.between(s_lo, s_hi)
    return sl.start, sl.stop


def viewer_script() -> str:
    """meshcat's viewer (three.js and the command decoder) as shipped with the package."""
    path = Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js"
    return path.read_text(encoding="utf-8")


_PAGE = """<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ margin: 0; font-family: sans-serif; }}
#meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
#caption {{ position: absolute; left: 12px; top: 10px; padding: 8px 12px; max-width: 42em;
  background: rgba(255, 255, 255, 0.85); border-radius: 6px; font-size: 14px; }}
</style></head>
<body>
<div id="meshcat-pane"></div>
<div id="caption"><b>{title}</b><br>{caption}</div>
<script>
{viewer}
</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
function e2eDecode(text) {{
  var raw = atob(text), bytes = new Uint8Array(raw.length);
  for (var i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
  return bytes;
}}
var e2eCommands = [
{commands}
];
for (var i = 0; i < e2eCommands.length; i++) viewer.handle_command_bytearray(e2eDecode(e2eCommands[i]));
</script>
</body>
</html>
"""


def export_html(ep: Episode, path: Path | str, caption: str = "") -> Path:
    """Write the episode's 3D replay as one self-contained HTML file (viewer and scene inlined;
    nothing is fetched, no server runs). ``caption`` (plain text) is shown over the scene."""
    window = build_scene(ep)
    commands = ",\n".join(f'"{base64.b64encode(c).decode("ascii")}"' for c in window.commands)
    ending = f"collided with a {ep.contact}" if ep.contact else "no collision"
    legend = "red box: the car; spheres: its proposed trajectory (0.3-1.5 s ahead)" + (
        "; one colour per GMM mode, bigger = heavier" if ep.modes is not None else ""
    )
    text = f"{html.escape(caption)}<br>{ep.seconds:.1f} s, {ending}. {legend}."
    page = _PAGE.format(
        title=html.escape(ep.name), caption=text, viewer=viewer_script(), commands=commands
    )
    path = Path(path)
    with atomic_write(path, "w") as f:
        f.write(page)
    return path


def export_gif(ep: Episode, path: Path | str, every: int = 2, scale: float = 0.75) -> Path:
    """The episode's camera views (with the proposals drawn) as an animated GIF, every
    ``every``-th decision, resized by ``scale``."""
    if not ep.frames:
        raise ValueError("the episode has no frames: record it with frames=True")
    pics = []
    for img in ep.frames[::every]:
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        pics.append(Image.fromarray(small))
    path = Path(path)
    ms = round(1000 * ep.period_s * every)
    with atomic_write(path) as f:
        rest = {"append_images": pics[1:], "duration": ms, "loop": 0, "optimize": True}
        pics[0].save(f, format="GIF", save_all=True, **rest)
    return path


def write_index(entries: list[tuple[str, str, str]], path: Path | str, title: str) -> Path:
    """An ``index.html`` linking the replays: ``entries`` of ``(driver, file name, one line)``."""
    rows = "\n".join(
        f'<li><a href="{html.escape(f)}">{html.escape(name)}</a>: {html.escape(line)}</li>'
        for name, f, line in entries
    )
    page = (
        f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f'</head>\n<body style="font-family: sans-serif; max-width: 52em; margin: 2em auto">\n'
        f"<h1>{html.escape(title)}</h1>\n<p>Each page is a standalone 3D replay (drag to orbit, "
        f"scroll to zoom; the animation controls are in the panel on the right).</p>\n"
        f"<ul>\n{rows}\n</ul>\n</body></html>\n"
    )
    path = Path(path)
    with atomic_write(path, "w") as f:
        f.write(page)
    return path
