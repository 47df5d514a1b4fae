"""What a synthetic dataset is: :class:`WorldSpec`, its parameters (rig, frames, size, seed, supersample,
lane, scene, random cameras, traffic, effects), checked when it is made; the kind and range of each
generation option (``data.generate.*`` of a training config, the flags of ``fisheyedepth-synthetic``); and
what ``synthetic.json`` records of a spec, which a finished dataset must match to be reused.

How a dataset is rendered (worker processes, LiDAR scans or not, a progress bar) is not part of its
spec: those are arguments of :func:`~.writer.generate` and :func:`~.writer.ensure_dataset`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..options import memory as option_memory
from ..options.kinds import SWITCH, Choice, Group, Kind, ListOf, Number, check_options
from ..options.memory import check_memory
from .rig import RIGS, make_rig
from .scene import LANES
from .sensor import EFFECTS, check_effects
from .traffic import DENSITY
from .world import SCENES

# The kind and range of each switch and number of the generation (``data.generate.*`` of a training
# config, the flags of ``fisheyedepth-synthetic``; fisheyedepth.options.kinds): checked before anything
# is rendered. ``worlds``: a mixed dataset's per-folder parameters, each of the same kinds.
_WORLD_OPTIONS: dict[str, Kind] = {
    "frames": Number(low=9, whole=True, note="3 per split"),
    "size": Number(low=16, whole=True),  # and a multiple of 8 (WorldSpec)
    "seed": Number(low=0, whole=True),
    "supersample": Number(low=1, whole=True),
    "workers": Number(low=0, whole=True),
    "lidar": SWITCH,
    "progress": SWITCH,
    "random_cameras": SWITCH,
    "traffic": DENSITY,
    "effects": ListOf(Choice(EFFECTS, note="each effect a switch, named alone"), single=True),
}
GENERATE_OPTIONS: dict[str, Kind] = _WORLD_OPTIONS | {"worlds": ListOf(Group(_WORLD_OPTIONS), optional=True)}
RENDERING = ("workers", "lidar", "progress")  # generation options that are not the dataset's spec
# Resident bytes while a dataset is rendered, the bounds of check_render_memory: per camera ray while a
# renderer is built and renders a frame (the rays, their hits on the ego body, a cast's hits and shading),
# measured with 512 to 1024 supersampled pixels a side: 190 to 270; per trajectory frame (its pose and its
# render job), measured with 20,000 and 100,000 frames: 2.4 to 2.9 kB.
RAY_BYTES = 190
FRAME_BYTES = 2400
# parameters a street dataset with fixed cameras does not write into synthetic.json (its files stay those
# of the versions before them): a finished dataset without the key was rendered with this value
UNWRITTEN = {"scene": "street", "random_cameras": False, "traffic": 0, "effects": []}
# the order of the parameters in synthetic.json
_WRITTEN = (
    *("seed", "rig", "size", "supersample", "frames"),
    *("lane", "scene", "random_cameras", "traffic", "effects"),
)


@dataclass(frozen=True)
class WorldSpec:
    """A synthetic dataset's parameters, checked when made: a ValueError names the first one not of its
    kind or range (``traffic: 9 is not a number in [0, 8] ...``; :meth:`from_config` names it as
    configured, ``data.generate.traffic``). ``effects`` is kept as a sorted tuple of names.

    ``rig``: one of :data:`~.rig.RIGS`. ``frames``: frames per camera over train, val and test together
    (at least 9). ``size``: image width and height in pixels (a multiple of 8, at least 16). ``seed``:
    the world's layout, textures and trajectory. ``supersample``: NxN rays per pixel. ``lane``: the car
    keeps to the "right" lane (KITTI-360: the right cameras see the near kerb, poles and facades) or the
    "left" one (the mirror situation). ``scene``: "street" (the city and the car) or "indoor" (a
    furnished room, a hand-held rig walking through it; ``lane`` does not apply). ``random_cameras``:
    every camera's model family, intrinsics, mounting height and tilt drawn from ``seed`` instead of the
    rig's own. ``traffic``: the density of moving cars and pedestrians (:mod:`.traffic`; 0: none, the
    world as before, bit for bit). ``effects``: names of :data:`.sensor.EFFECTS` (auto-exposure, white
    balance, vignetting, noise, motion blur), each a switch."""

    rig: str = "kitti360"
    frames: int = 200
    size: int = 256
    seed: int = 0
    supersample: int = 2
    lane: str = "right"
    scene: str = "street"
    random_cameras: bool = False
    traffic: float = 0.0
    effects: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_options(self._values(), GENERATE_OPTIONS)
        if self.rig not in RIGS:
            raise ValueError(f"unknown rig {self.rig!r}; one of {RIGS}")
        if self.size < 16 or self.size % 8:
            raise ValueError(f"size must be a multiple of 8 and at least 16, got {self.size}")
        if self.lane not in LANES:
            raise ValueError(f"lane must be one of {LANES}, got {self.lane!r}")
        if self.scene not in SCENES:
            raise ValueError(f"scene must be one of {SCENES}, got {self.scene!r}")
        object.__setattr__(self, "effects", check_effects(self.effects))

    def _values(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in SPEC_FIELDS}

    @classmethod
    def from_config(cls, options: Mapping[str, Any], prefix: str = "data.generate.") -> WorldSpec:
        """The spec of a ``data.generate`` mapping without its ``worlds`` (a mixed dataset's folder: the
        shared keys with its world's over them). Its rendering options (:data:`RENDERING`) are left to
        the caller; a value not of its kind or range, and a key that is no option, are named as
        configured (``prefix`` + key)."""
        check_options(options, GENERATE_OPTIONS, prefix)
        unknown = [key for key in options if key not in SPEC_FIELDS and key not in RENDERING]
        if unknown:
            raise ValueError(
                f"{prefix}{unknown[0]}: not an option of the synthetic dataset; "
                f"its options are {', '.join([*SPEC_FIELDS, *RENDERING])}"
            )
        return cls(**{key: value for key, value in options.items() if key in SPEC_FIELDS})

    def params(self) -> dict[str, Any]:
        """Every parameter by name, ``effects`` a list (as ``synthetic.json`` and a config hold it)."""
        return self._values() | {"effects": list(self.effects)}

    def written(self) -> dict[str, Any]:
        """The parameters ``synthetic.json`` records: all but those of :data:`UNWRITTEN` at their value."""
        params = self.params()
        return {k: params[k] for k in _WRITTEN if k not in UNWRITTEN or params[k] != UNWRITTEN[k]}

    @classmethod
    def from_written(cls, meta: Mapping[str, Any]) -> WorldSpec:
        """The spec a dataset's ``synthetic.json`` records (:meth:`written`); a parameter it lacks has its
        :data:`UNWRITTEN` value, or the default."""
        return cls(**{k: v for k, v in {**UNWRITTEN, **meta}.items() if k in SPEC_FIELDS})

    def differences(self, meta: Mapping[str, Any]) -> list[str]:
        """Each parameter in which a dataset's ``synthetic.json`` differs from this spec, as ``size 16
        (asked 24)``; one it lacks (an older version's) is not compared."""
        meta, asked = {**UNWRITTEN, **meta}, self.params()
        return [f"{k} {meta[k]!r} (asked {asked[k]!r})" for k in asked if k in meta and meta[k] != asked[k]]


SPEC_FIELDS = tuple(field.name for field in dataclasses.fields(WorldSpec))  # the parameters, in order


def render_memory(size: int, supersample: int, cameras: int, renderers: int = 1) -> int:
    """Bytes that rendering holds: ``renderers * cameras * ((supersample * size)^2 + size^2) *``
    :data:`RAY_BYTES`. Every renderer (the rendering process's, and with 2 workers or more one in each
    worker process) holds each camera's supersampled rays and its pixel-centre rays (the ground truth)."""
    return renderers * cameras * ((supersample * size) ** 2 + size**2) * RAY_BYTES


def check_render_memory(options: Mapping[str, Any], prefix: str = "") -> None:
    """A ValueError naming (``prefix`` + option) ``frames``, ``size``, ``supersample`` or ``workers`` of
    the generation ``options`` (each of its kind already; a mixed dataset's ``worlds`` each over the
    shared ones) when rendering would need more memory than this machine has: ``frames *``
    :data:`FRAME_BYTES` for the trajectory, :func:`render_memory` for the rays. The rays' need is named
    by ``size`` when it is too large even without supersampling, by ``supersample`` when it is too large
    in one process, else by ``workers``."""
    shared = {k: v for k, v in options.items() if k != "worlds"}
    worlds = options.get("worlds") or [{}]
    defaults = {field.name: field.default for field in dataclasses.fields(WorldSpec)} | {"workers": 0}
    for i, world in enumerate(worlds):
        params = defaults | shared | dict(world)
        name = {k: f"{prefix}worlds[{i}].{k}" if k in world else f"{prefix}{k}" for k in params}
        frames = params["frames"]
        what = f"its trajectory and a render job a frame, {FRAME_BYTES} bytes each"
        check_memory(name["frames"], frames, frames * FRAME_BYTES, what)
        if params["rig"] not in RIGS:
            continue  # WorldSpec names it
        size, supersample, workers = params["size"], params["supersample"], params["workers"]
        cameras = len(make_rig(params["rig"], 16).cameras)
        renderers = 1 + workers if workers > 1 else 1
        need = render_memory(size, supersample, cameras, renderers)
        key, have = "workers", option_memory.machine_memory()
        if render_memory(size, 1, cameras) > have:
            key = "size"
        elif render_memory(size, supersample, cameras) > have:
            key = "supersample"
        what = (
            f"{renderers} renderer(s) x {cameras} cameras x ({supersample * size}^2 supersampled + "
            f"{size}^2 centre) rays x {RAY_BYTES} bytes"
        )
        check_memory(name[key], params[key], need, what)
