"""Procedural analytic scenes (indoor room, outdoor street): the :class:`Scene` and its makers.

World frame: metres, OpenCV-like axes with gravity along +y: x right, y *down*, z forward. The
floor / ground is the plane y = 0, so a camera held 1.5 m above the floor sits at y = -1.5 and an
identity rotation is an upright camera looking along +z.

A :class:`Scene` is a handful of primitive arrays (float64, world frame):

* ``room``: an axis-aligned box seen from inside (floor, ceiling, four walls), 6 faces;
* ``ground``: the plane y = 0 seen from above (road for |x| < ``road_half_width``, else pavement);
* ``boxes`` (K, 7): centre xyz, half extents xyz, yaw about the y axis (radians);
* ``spheres`` (K, 4): centre xyz, radius;
* ``cylinders`` (K, 5): axis x, axis z, y_top, y_bottom (y_top < y_bottom, y is down), radius;
  vertical, capped;
* ``sky`` (4,): centre xyz, radius of a sphere seen from inside, fixed in the world, so sky points
  are real, consistent 3-D points at a large distance.

Every object has its own material (row of :attr:`Scene.materials`, columns ``MAT_*``), so ids
double as object ids. :func:`make_indoor_scene` / :func:`make_outdoor_scene` build a random scene
around a camera path, deterministic for a seed. Ray casting against a scene
lives in :mod:`raytun3r_plugin.synthetic.raycast`.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, field

import numpy as np

from raytun3r_plugin.errors import InputError

__all__ = [
    "Scene",
    "make_indoor_scene",
    "make_outdoor_scene",
    "make_scene",
]

# Material table columns.
MAT_BASE = slice(0, 3)
MAT_SPOT = slice(3, 6)
MAT_FREQ = 6
MAT_OFFSET = slice(7, 10)
MAT_CONTRAST = 10
MAT_SPOT_THRESHOLD = 11
MAT_EMISSIVE = 12
MAT_COLOUR_VAR = 13
MAT_DIM = 14


@dataclass
class Scene:
    """An analytic scene; see the module docstring for the layout of every array."""

    kind: str
    seed: int
    materials: np.ndarray  # (M, MAT_DIM) float32
    boxes: np.ndarray  # (K, 7)
    box_materials: np.ndarray  # (K,) int
    spheres: np.ndarray  # (K, 4)
    sphere_materials: np.ndarray  # (K,) int
    cylinders: np.ndarray  # (K, 5)
    cylinder_materials: np.ndarray  # (K,) int
    room: np.ndarray | None = None  # (6,) lo xyz, hi xyz
    room_materials: np.ndarray | None = None  # (6,) faces -x, +x, -y (ceiling), +y (floor), -z, +z
    ground: bool = False
    ground_materials: np.ndarray | None = None  # (2,) road, pavement
    road_half_width: float = 4.0
    sky: np.ndarray | None = None  # (4,) centre xyz, radius
    sky_material: int = -1
    light_dir: np.ndarray = field(default_factory=lambda: np.array([0.3, 1.0, 0.45]))  # travel dir
    ambient: float = 0.4
    params: dict = field(default_factory=dict)  # generation parameters (kind, seed, path extent)

    @property
    def n_materials(self) -> int:
        """Number of materials (= objects, counting each room face separately)."""
        return int(self.materials.shape[0])


# --------------------------------------------------------------------------------------------
# Scene generation
# --------------------------------------------------------------------------------------------


class _Materials:
    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.rows: list[np.ndarray] = []

    def add(
        self,
        value: tuple[float, float] = (0.35, 0.9),
        saturation: tuple[float, float] = (0.15, 0.75),
        freq: tuple[float, float] = (1.5, 4.0),
        hue: float | None = None,
        contrast: tuple[float, float] = (0.5, 0.9),
        emissive: bool = False,
    ) -> int:
        """Append a random material; returns its id."""
        rng = self.rng
        h = rng.uniform() if hue is None else hue
        s = rng.uniform(*saturation)
        v = rng.uniform(*value)
        base = colorsys.hsv_to_rgb(h, s, v)
        hs = (h + rng.uniform(0.25, 0.75)) % 1.0
        vs = (
            v * rng.uniform(0.3, 0.6)
            if rng.uniform() < 0.6
            else min(1.0, v * rng.uniform(1.3, 1.8) + 0.1)
        )
        spot = colorsys.hsv_to_rgb(hs, rng.uniform(0.2, 0.9), vs)
        row = np.zeros(MAT_DIM, dtype=np.float32)
        row[MAT_BASE] = base
        row[MAT_SPOT] = spot
        row[MAT_FREQ] = rng.uniform(*freq)
        row[MAT_OFFSET] = rng.uniform(0.0, 256.0, size=3)
        row[MAT_CONTRAST] = rng.uniform(*contrast)
        row[MAT_SPOT_THRESHOLD] = rng.uniform(0.6, 0.7)
        row[MAT_EMISSIVE] = 1.0 if emissive else 0.0
        row[MAT_COLOUR_VAR] = rng.uniform(0.15, 0.35)
        self.rows.append(row)
        return len(self.rows) - 1

    def table(self) -> np.ndarray:
        return np.stack(self.rows).astype(np.float32)


def _path_xz(path: np.ndarray | None) -> np.ndarray:
    if path is None or len(path) == 0:
        return np.zeros((1, 2))
    return np.asarray(path, dtype=np.float64)[:, [0, 2]]


def _clear_of(path_xz: np.ndarray, xz: np.ndarray, radius: float, clearance: float) -> bool:
    """True if a footprint of ``radius`` around ``xz`` keeps ``clearance`` from every path point."""
    return bool(np.min(np.linalg.norm(path_xz - xz[None], axis=1)) > radius + clearance)


def _overlaps_a_box(x: float, z: float, radius: float, boxes: list) -> bool:
    """True if a footprint of ``radius`` at (x, z) reaches the footprint circle of one of
    ``boxes`` (``[x, y, z, hx, hy, hz, yaw]`` each)."""
    return any(math.hypot(x - b[0], z - b[2]) < radius + math.hypot(b[3], b[5]) for b in boxes)


@dataclass(frozen=True)
class _Floor:
    """A room's floor plan (metres, x across and z along): where furniture may stand."""

    xmin: float
    xmax: float
    zmin: float
    zmax: float
    margin: float = 0.05

    def inside(self, x: float, z: float, rad: float) -> bool:
        """Whether a piece of radius ``rad`` at (x, z) stands clear of the walls."""
        return (
            self.xmin + rad + self.margin <= x <= self.xmax - rad - self.margin
            and self.zmin + rad + self.margin <= z <= self.zmax - rad - self.margin
        )


def _place_boxes(
    rng: np.random.Generator, mats: _Materials, floor: _Floor, pxz: np.ndarray, height: float
) -> tuple[list, list]:
    """7-10 boxes (tables, cabinets, shelves), half of them against a wall, none overlapping
    another or within 0.5 m of the camera path: ``(boxes, their materials)``."""
    boxes: list = []
    box_m: list = []
    margin = floor.margin
    n_boxes = int(rng.integers(7, 11))
    tries = 0
    while len(boxes) < n_boxes and tries < 500:
        tries += 1
        hx, hz = rng.uniform(0.2, 0.9), rng.uniform(0.2, 0.7)
        hy = rng.uniform(0.2, min(1.0, height / 2 - 0.2))
        rad = math.hypot(hx, hz)
        if rng.uniform() < 0.5:  # against a wall
            side = int(rng.integers(4))
            x = rng.uniform(floor.xmin + rad, floor.xmax - rad)
            z = rng.uniform(floor.zmin + rad, floor.zmax - rad)
            if side == 0:
                x = floor.xmin + rad + margin
            elif side == 1:
                x = floor.xmax - rad - margin
            elif side == 2:
                z = floor.zmin + rad + margin
            else:
                z = floor.zmax - rad - margin
        else:
            x = rng.uniform(floor.xmin + rad, floor.xmax - rad)
            z = rng.uniform(floor.zmin + rad, floor.zmax - rad)
        if not floor.inside(x, z, rad) or not _clear_of(pxz, np.array([x, z]), rad, 0.5):
            continue
        if _overlaps_a_box(x, z, rad, boxes):
            continue
        boxes.append([x, -hy, z, hx, hy, hz, rng.uniform(-0.6, 0.6)])
        box_m.append(mats.add())
    return boxes, box_m


def _place_spheres(
    rng: np.random.Generator,
    mats: _Materials,
    floor: _Floor,
    pxz: np.ndarray,
    height: float,
    boxes: list,
) -> tuple[list, list]:
    """3-5 spheres, on the floor or resting on a box top: ``(spheres, their materials)``."""
    spheres: list = []
    sph_m: list = []
    for _ in range(int(rng.integers(3, 6))):
        for _try in range(100):
            rad = rng.uniform(0.15, 0.45)
            if boxes and rng.uniform() < 0.5:
                b = boxes[int(rng.integers(len(boxes)))]
                x, z, y = b[0], b[2], -2 * b[4] - rad
            else:
                x, z, y = (
                    rng.uniform(floor.xmin, floor.xmax),
                    rng.uniform(floor.zmin, floor.zmax),
                    -rad,
                )
            if y - rad < -height + 0.05 or not floor.inside(x, z, rad):
                continue
            if not _clear_of(pxz, np.array([x, z]), rad, 0.5):
                continue
            spheres.append([x, y, z, rad])
            sph_m.append(mats.add(freq=(3.0, 6.0)))
            break
    return spheres, sph_m


def _place_cylinders(
    rng: np.random.Generator,
    mats: _Materials,
    floor: _Floor,
    pxz: np.ndarray,
    height: float,
    boxes: list,
) -> tuple[list, list]:
    """3-5 cylinders (pillars to the ceiling, stools, lamps) clear of the boxes:
    ``(cylinders, their materials)``."""
    cyls: list = []
    cyl_m: list = []
    for _ in range(int(rng.integers(3, 6))):
        for _try in range(100):
            rad = rng.uniform(0.08, 0.35)
            x, z = rng.uniform(floor.xmin, floor.xmax), rng.uniform(floor.zmin, floor.zmax)
            y_top = -height if rng.uniform() < 0.4 else -rng.uniform(0.4, 1.8)
            if not floor.inside(x, z, rad) or not _clear_of(pxz, np.array([x, z]), rad, 0.5):
                continue
            if _overlaps_a_box(x, z, rad, boxes):
                continue
            cyls.append([x, z, y_top, 0.0, rad])
            cyl_m.append(mats.add(freq=(2.0, 5.0)))
            break
    return cyls, cyl_m


def make_indoor_scene(seed: int, path: np.ndarray | None = None) -> Scene:
    """A furnished room around the camera path ``path`` (N, 3) world positions (or the origin).

    The room (about 7-9 m wide, 2.6-3.2 m high, at least 9 m deep and 2.5 m beyond the path)
    holds 7-10 boxes (tables, cabinets, shelves), 3-5 spheres and 3-5 cylinders (pillars, stools,
    lamps), all kept at least 0.5 m from the camera path.
    """
    rng = np.random.default_rng([int(seed), 1])
    mats = _Materials(rng)
    pxz = _path_xz(path)
    width = rng.uniform(7.0, 9.0)
    height = rng.uniform(2.6, 3.2)
    zmin = min(-4.5, float(pxz[:, 1].min()) - 2.5)
    zmax = max(4.5, float(pxz[:, 1].max()) + 2.5)
    xmin = min(-width / 2, float(pxz[:, 0].min()) - 2.0)
    xmax = max(width / 2, float(pxz[:, 0].max()) + 2.0)
    room = np.array([xmin, -height, zmin, xmax, 0.0, zmax])
    room_mats = np.array(
        [
            mats.add(value=(0.5, 0.85), freq=(1.0, 2.5)),  # -x wall
            mats.add(value=(0.5, 0.85), freq=(1.0, 2.5)),  # +x wall
            mats.add(value=(0.7, 0.95), saturation=(0.0, 0.2), freq=(1.0, 2.0)),  # ceiling
            mats.add(
                value=(0.3, 0.65), saturation=(0.3, 0.7), freq=(2.0, 4.0), contrast=(0.7, 1.0)
            ),  # floor
            mats.add(value=(0.5, 0.85), freq=(1.0, 2.5)),  # -z wall
            mats.add(value=(0.5, 0.85), freq=(1.0, 2.5)),  # +z wall
        ]
    )
    bounds = _Floor(xmin, xmax, zmin, zmax)
    boxes, box_m = _place_boxes(rng, mats, bounds, pxz, height)
    spheres, sph_m = _place_spheres(rng, mats, bounds, pxz, height, boxes)
    cyls, cyl_m = _place_cylinders(rng, mats, bounds, pxz, height, boxes)
    light = np.array([rng.uniform(-0.5, 0.5), 1.0, rng.uniform(-0.5, 0.5)])
    return Scene(
        kind="indoor",
        seed=int(seed),
        materials=mats.table(),
        boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7),
        box_materials=np.array(box_m, dtype=np.int64),
        spheres=np.array(spheres, dtype=np.float64).reshape(-1, 4),
        sphere_materials=np.array(sph_m, dtype=np.int64),
        cylinders=np.array(cyls, dtype=np.float64).reshape(-1, 5),
        cylinder_materials=np.array(cyl_m, dtype=np.int64),
        room=room,
        room_materials=room_mats,
        light_dir=light / np.linalg.norm(light),
        ambient=0.45,
        params={"kind": "indoor", "seed": int(seed)},
    )


def _place_buildings(
    rng: np.random.Generator,
    mats: _Materials,
    side: float,
    z0: float,
    z1: float,
    boxes: list,
    box_m: list,
) -> None:
    """Facades along one ``side`` (-1 left, +1 right) of the street from z0 to z1 m, appended to
    ``boxes`` and their materials to ``box_m``."""
    z = z0
    while z < z1:
        w = rng.uniform(5.0, 14.0)
        if rng.uniform() < 0.15:
            z += rng.uniform(2.0, 5.0)  # gap between buildings
        front = rng.uniform(9.0, 10.5)
        depth = rng.uniform(6.0, 12.0)
        h = rng.uniform(5.0, 25.0)
        x = side * (front + depth / 2)
        boxes.append([x, -h / 2, z + w / 2, depth / 2, h / 2, w / 2, 0.0])
        box_m.append(mats.add(freq=(0.6, 2.0), value=(0.35, 0.9)))
        z += w


def _place_cars(
    rng: np.random.Generator,
    mats: _Materials,
    side: float,
    z0: float,
    z1: float,
    pxz: np.ndarray,
    boxes: list,
    box_m: list,
) -> None:
    """Parked cars along one ``side`` of the street, clear of the camera path, appended as
    boxes."""
    z = z0 + rng.uniform(0.0, 6.0)
    while z < z1:  # parked cars
        if rng.uniform() < 0.6:
            x = side * rng.uniform(5.2, 5.8)
            if _clear_of(pxz, np.array([x, z]), 2.5, 1.0):
                hy = rng.uniform(0.65, 0.85)
                boxes.append(
                    [
                        x,
                        -hy,
                        z,
                        rng.uniform(0.85, 1.0),
                        hy,
                        rng.uniform(2.0, 2.5),
                        rng.uniform(-0.08, 0.08),
                    ]
                )
                box_m.append(mats.add(freq=(2.0, 5.0), saturation=(0.3, 0.9)))
        z += rng.uniform(6.0, 10.0)


def _place_poles(
    rng: np.random.Generator,
    mats: _Materials,
    side: float,
    z0: float,
    z1: float,
    pxz: np.ndarray,
    poles: tuple[list, list],
    crowns: tuple[list, list],
) -> None:
    """Poles along one ``side`` of the street, half of them trees: the poles appended to
    ``poles`` (cylinders, materials), the trees' crowns to ``crowns`` (spheres, materials)."""
    cyls, cyl_m = poles
    balls, ball_m = crowns
    z = z0 + rng.uniform(0.0, 10.0)
    while z < z1:  # poles, half of them trees
        x = side * rng.uniform(6.7, 7.3)
        if _clear_of(pxz, np.array([x, z]), 1.5, 1.0):
            tree = rng.uniform() < 0.5
            top = -rng.uniform(3.0, 4.5) if tree else -rng.uniform(4.0, 7.0)
            cyls.append([x, z, top, 0.0, rng.uniform(0.08, 0.18)])
            cyl_m.append(mats.add(freq=(3.0, 6.0)))
            if tree:
                r = rng.uniform(1.0, 1.6)
                balls.append([x, top - r * 0.8, z, r])
                ball_m.append(
                    mats.add(hue=rng.uniform(0.2, 0.4), saturation=(0.4, 0.8), freq=(2.0, 4.0))
                )
        z += rng.uniform(8.0, 16.0)


def make_outdoor_scene(seed: int, path: np.ndarray | None = None) -> Scene:
    """A street along +z around the camera path ``path`` (N, 3) (or the origin).

    Ground plane (road |x| < 4 m, pavement beyond), building facades on both sides (boxes from
    |x| = 9-10.5 m outwards, 5-14 m wide, 5-25 m high, small gaps), parked cars (boxes) at
    |x| = 5.5 m, poles (cylinders) at |x| = 7 m, some with a tree crown (sphere), and a sky sphere
    of radius 2 km fixed in the world. Everything keeps at least 1 m from the camera path.
    """
    rng = np.random.default_rng([int(seed), 2])
    mats = _Materials(rng)
    pxz = _path_xz(path)
    z0 = float(pxz[:, 1].min()) - 30.0
    z1 = float(pxz[:, 1].max()) + 80.0
    road = mats.add(
        value=(0.25, 0.45), saturation=(0.0, 0.15), freq=(1.5, 3.0), contrast=(0.7, 1.0)
    )
    pave = mats.add(value=(0.45, 0.7), saturation=(0.05, 0.3), freq=(1.5, 3.0), contrast=(0.7, 1.0))
    sky = mats.add(
        value=(0.85, 0.95),
        saturation=(0.25, 0.45),
        hue=rng.uniform(0.55, 0.62),
        emissive=True,
        freq=(0.004, 0.006),
    )
    boxes, box_m = [], []
    spheres, sph_m = [], []
    cyls, cyl_m = [], []
    for side in (-1.0, 1.0):
        # The order of the three is the order of the random draws: a scene is a function of its seed.
        _place_buildings(rng, mats, side, z0, z1, boxes, box_m)
        _place_cars(rng, mats, side, z0, z1, pxz, boxes, box_m)
        _place_poles(rng, mats, side, z0, z1, pxz, (cyls, cyl_m), (spheres, sph_m))
    sun = np.array([rng.uniform(-0.6, 0.6), 1.0, rng.uniform(-0.3, 0.6)])
    zc = 0.5 * (z0 + z1)
    return Scene(
        kind="outdoor",
        seed=int(seed),
        materials=mats.table(),
        boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7),
        box_materials=np.array(box_m, dtype=np.int64),
        spheres=np.array(spheres, dtype=np.float64).reshape(-1, 4),
        sphere_materials=np.array(sph_m, dtype=np.int64),
        cylinders=np.array(cyls, dtype=np.float64).reshape(-1, 5),
        cylinder_materials=np.array(cyl_m, dtype=np.int64),
        ground=True,
        ground_materials=np.array([road, pave], dtype=np.int64),
        road_half_width=4.0,
        sky=np.array([0.0, 0.0, zc, 2000.0]),
        sky_material=sky,
        light_dir=sun / np.linalg.norm(sun),
        ambient=0.5,
        params={"kind": "outdoor", "seed": int(seed)},
    )


def make_scene(kind: str, seed: int, path: np.ndarray | None = None) -> Scene:
    """``make_indoor_scene`` or ``make_outdoor_scene`` by ``kind`` ("indoor" | "outdoor")."""
    if kind == "indoor":
        return make_indoor_scene(seed, path)
    if kind == "outdoor":
        return make_outdoor_scene(seed, path)
    raise InputError(f"unknown scene kind {kind!r}; expected 'indoor' or 'outdoor'")
