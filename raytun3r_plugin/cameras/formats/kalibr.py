"""Kalibr camchain YAML (``cam0: {camera_model, intrinsics, distortion_model, ...}``): pinhole
with no, radtan or equidistant distortion, omni (MEI, or UCM without distortion), ds and eucm."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from raytun3r_plugin._strict import quote
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.formats._fields import (
    _SHORT,
    PathLike,
    _build,
    _fail,
    _get,
    _int,
    _num,
    _numbers,
)
from raytun3r_plugin.cameras.formats.yaml_formats import _is_cam_key
from raytun3r_plugin.cameras.kb import KannalaBrandt4
from raytun3r_plugin.cameras.pinhole import OpenCVRadTan, Pinhole
from raytun3r_plugin.cameras.unified import EUCM, MEI, UCM, DoubleSphere


def _read_kalibr(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> Camera:
    entry = _KalibrEntry.parse(path, d, _kalibr_key(path, d, camera))
    reader = _KALIBR_MODELS.get(entry.camera_model)
    if reader is None:
        raise _fail(
            path,
            f"{entry.key}.camera_model",
            f"unsupported camera model {quote(entry.camera_model, _SHORT)} (supported: "
            f"{', '.join(_KALIBR_MODELS)})",
        )
    return reader(entry)


def _kalibr_key(path: PathLike, d: Mapping[str, Any], camera: str | int | None) -> str:
    """The ``camN`` entry asked for (default ``cam0``, else the first)."""
    names = sorted((k for k in d if _is_cam_key(k)), key=lambda k: int(k[3:]))
    if camera is None:
        return "cam0" if "cam0" in names else names[0]
    if isinstance(camera, int) and not isinstance(camera, bool) and f"cam{camera}" in names:
        return f"cam{camera}"
    if isinstance(camera, str) and (camera in names or f"cam{camera}" in names):
        return camera if camera in names else f"cam{camera}"
    raise _fail(
        path,
        "camera",
        f"unknown camera id {quote(camera, _SHORT)} (available: {quote(names, _SHORT)})",
    )


@dataclass
class _KalibrEntry:
    """One ``camN`` entry, its models checked and its resolution read."""

    path: PathLike
    key: str
    entry: Mapping[str, Any]
    camera_model: str
    distortion_model: str
    width: int
    height: int

    @classmethod
    def parse(cls, path: PathLike, d: Mapping[str, Any], key: str) -> _KalibrEntry:
        c = d[key]
        if not isinstance(c, Mapping):
            raise _fail(path, key, "expected a mapping")
        cam_model = _get(path, c, "camera_model", f"{key}.camera_model")
        if not isinstance(cam_model, str):
            raise _fail(
                path, f"{key}.camera_model", f"expected a string, got {quote(cam_model, _SHORT)}"
            )
        dist_model = c.get("distortion_model", "none")
        if dist_model is None:
            dist_model = "none"
        if not isinstance(dist_model, str):
            raise _fail(
                path,
                f"{key}.distortion_model",
                f"expected a string, got {quote(dist_model, _SHORT)}",
            )
        # Kalibr's command line says "equi" for what its camchain files call "equidistant".
        dist_model = {"equi": "equidistant"}.get(dist_model, dist_model)
        res = _numbers(
            path,
            _get(path, c, "resolution", f"{key}.resolution"),
            f"{key}.resolution",
            2,
            "width height",
        )
        w = _int(path, f"{key}.resolution[0]", res[0])
        h = _int(path, f"{key}.resolution[1]", res[1])
        if dist_model not in ("none", "radtan", "equidistant"):
            raise _fail(
                path,
                f"{key}.distortion_model",
                f"unsupported distortion model {quote(dist_model, _SHORT)} (supported: none, "
                "radtan, equidistant)",
            )
        return cls(path, key, c, cam_model, dist_model, w, h)

    @property
    def intr_field(self) -> str:
        return f"{self.key}.intrinsics"

    @property
    def dist_field(self) -> str:
        return f"{self.key}.distortion_coeffs"

    def intrinsics(self, count: int, names: str) -> list[float]:
        """The ``intrinsics`` list, ``count`` numbers named ``names`` in messages."""
        raw = _get(self.path, self.entry, "intrinsics", self.intr_field)
        return _numbers(self.path, raw, self.intr_field, count, names)

    def distortion(self, count: int, names: str) -> list[float]:
        """The ``distortion_coeffs`` list, ``count`` numbers named ``names`` in messages."""
        raw = _get(self.path, self.entry, "distortion_coeffs", self.dist_field)
        return _numbers(self.path, raw, self.dist_field, count, names)

    def no_distortion(self) -> None:
        """Refuse non-zero ``distortion_coeffs`` under ``distortion_model: none``."""
        coeffs = self.entry.get("distortion_coeffs", [])
        if coeffs is None:
            return
        if not isinstance(coeffs, list):
            raise _fail(self.path, self.dist_field, f"expected a list, got {quote(coeffs, _SHORT)}")
        if any(_num(self.path, f"{self.dist_field}[{i}]", x) != 0.0 for i, x in enumerate(coeffs)):
            raise _fail(self.path, self.dist_field, "must be empty for distortion_model 'none'")

    def only_without_distortion(self) -> None:
        if self.distortion_model != "none":
            raise _fail(
                self.path,
                f"{self.key}.distortion_model",
                f"camera_model {quote(self.camera_model, _SHORT)} supports distortion_model "
                "none only",
            )
        self.no_distortion()

    def fields(self, ours: tuple[str, ...], theirs: tuple[str, ...]) -> dict[str, str]:
        """Our parameter name -> the intrinsics entry it came from (for error messages)."""
        return {
            n: f"{self.intr_field}[{i}] ({k})"
            for i, (n, k) in enumerate(zip(ours, theirs, strict=True))
        }

    def distortion_fields(self, ours: tuple[str, ...]) -> dict[str, str]:
        return {n: f"{self.dist_field}[{i}] ({n})" for i, n in enumerate(ours)}

    def build(self, cls: type[Camera], values: dict[str, float], fields: dict[str, str]) -> Camera:
        return _build(self.path, cls, self.width, self.height, values, fields)


def _kalibr_pinhole(e: _KalibrEntry) -> Camera:
    """``pinhole`` with ``none`` (Pinhole), ``radtan`` (OpenCV) or ``equidistant`` (KB4)."""
    fu, fv, pu, pv = e.intrinsics(4, "fu fv pu pv")
    base = {"fx": fu, "fy": fv, "cx": pu, "cy": pv}
    fields = e.fields(("fx", "fy", "cx", "cy"), ("fu", "fv", "pu", "pv"))
    if e.distortion_model == "none":
        e.no_distortion()
        return e.build(Pinhole, base, fields)
    if e.distortion_model == "radtan":
        k1, k2, r1, r2 = e.distortion(4, "k1 k2 r1 r2")
        fields |= e.distortion_fields(("k1", "k2", "p1", "p2"))
        return e.build(OpenCVRadTan, base | {"k1": k1, "k2": k2, "p1": r1, "p2": r2}, fields)
    ks = e.distortion(4, "k1 k2 k3 k4")
    fields |= e.distortion_fields(("k1", "k2", "k3", "k4"))
    return e.build(
        KannalaBrandt4, base | dict(zip(("k1", "k2", "k3", "k4"), ks, strict=True)), fields
    )


def _kalibr_omni(e: _KalibrEntry) -> Camera:
    """``omni``: MEI with ``radtan``, UCM (alpha form) without distortion."""
    xi, fu, fv, pu, pv = e.intrinsics(5, "xi fu fv pu pv")
    fields = e.fields(("xi", "fx", "fy", "cx", "cy"), ("xi", "fu", "fv", "pu", "pv"))
    if e.distortion_model == "radtan":
        k1, k2, r1, r2 = e.distortion(4, "k1 k2 r1 r2")
        fields |= e.distortion_fields(("k1", "k2", "p1", "p2"))
        values = {"fx": fu, "fy": fv, "cx": pu, "cy": pv, "xi": xi}
        return e.build(MEI, values | {"k1": k1, "k2": k2, "p1": r1, "p2": r2}, fields)
    if e.distortion_model == "none":
        e.no_distortion()
        # xi form -> alpha form: alpha = xi / (1 + xi), f_alpha = f_xi / (1 + xi).
        if not (math.isfinite(xi) and xi >= 0.0):
            raise _fail(
                e.path, fields["xi"], f"must be a finite number >= 0, got {quote(xi, _SHORT)}"
            )
        values = {
            "fx": fu / (1.0 + xi),
            "fy": fv / (1.0 + xi),
            "cx": pu,
            "cy": pv,
            "alpha": xi / (1.0 + xi),
        }
        return e.build(UCM, values, fields | {"alpha": fields["xi"]})
    raise _fail(
        e.path,
        f"{e.key}.distortion_model",
        "camera_model 'omni' supports distortion_model none or radtan",
    )


def _kalibr_unified(e: _KalibrEntry) -> Camera:
    """``ds`` (double sphere) and ``eucm``, without distortion."""
    e.only_without_distortion()
    first = ("xi", "alpha") if e.camera_model == "ds" else ("alpha", "beta")
    values = e.intrinsics(6, f"{first[0]} {first[1]} fu fv pu pv")
    order = (*first, "fx", "fy", "cx", "cy")
    fields = {n: f"{e.intr_field}[{i}] ({n})" for i, n in enumerate(order)}
    cls = DoubleSphere if e.camera_model == "ds" else EUCM
    return e.build(cls, dict(zip(order, values, strict=True)), fields)


_KALIBR_MODELS: dict[str, Callable[[_KalibrEntry], Camera]] = {
    "pinhole": _kalibr_pinhole,
    "omni": _kalibr_omni,
    "ds": _kalibr_unified,
    "eucm": _kalibr_unified,
}
