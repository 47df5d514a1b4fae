"""Rendering a synthetic dataset in the KITTI-360 layout (see docs/data-format.md): :func:`generate`
renders one into a folder, :func:`ensure_dataset` is the first-use variant for training that reuses a
finished dataset rendered with the same parameters and never replaces a folder this generator did not
make, :func:`ensure_datasets` does it for each folder of a data config.

The scene comes from :mod:`.scene`, the frames are rendered by :mod:`.pool`'s workers with
:mod:`.frames`' renderer, and written into :mod:`.folder`'s temporary folder in :mod:`.layout`'s layout.
"""

from __future__ import annotations

import os
from pathlib import Path

from tqdm import tqdm

from ..option_checks import check_options
from .folder import (
    check_parameters,
    finish,
    is_complete,
    is_empty_dir,
    made_by_generator,
    partial_folder,
    refusal,
    temporary_folder,
)
from .frames import FrameRenderer
from .layout import metadata, write_layout
from .pool import render_jobs, sigterm_raises
from .rig import RIGS
from .scene import LANES, make_scene_motion, make_scene_world, split_frames, split_jobs
from .sensor import check_effects
from .spec import GENERATE_OPTIONS
from .world import SCENES


def generate(
    out: str | os.PathLike,
    rig: str = "kitti360",
    frames: int = 200,
    size: int = 256,
    seed: int = 0,
    supersample: int = 2,
    workers: int = 0,
    lidar: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    lane: str = "right",
    scene: str = "street",
    random_cameras: bool = False,
    traffic: float = 0.0,
    effects=(),
) -> Path:
    """Render ``frames`` frames of every camera of ``rig`` (plus LiDAR) into ``out``. Returns ``out``.

    ``lane``: the car keeps to the "right" lane (KITTI-360: the right cameras see the near kerb,
    poles and facades) or the "left" one (the mirror situation, for per-camera comparisons).
    ``scene``: "street" (the city and the car) or "indoor" (a furnished room, a hand-held rig walking
    through it; ``lane`` does not apply). ``random_cameras``: every camera's model family, intrinsics,
    mounting height and tilt drawn from ``seed`` instead of the rig's own (``rig.random_camera``).
    ``traffic``: the density of moving cars and pedestrians (:mod:`.traffic`; 0: none, the world as
    before, bit for bit); with traffic, ``data_2d_moving`` holds each frame's mask of pixels that see a
    moving agent. ``effects``: names of :data:`.sensor.EFFECTS` (auto-exposure, white balance,
    vignetting, noise, motion blur), each a switch; none by default.

    ``overwrite`` replaces whatever ``out`` holds once the new dataset is complete (the CLI's explicit
    ``--overwrite``); ``ensure_dataset`` is the careful variant that replaces only what this generator made.
    SIGTERM or Ctrl-C stops the workers, removes the temporary folder and re-raises (``Terminated``).
    """
    check_options(locals(), GENERATE_OPTIONS)
    out = Path(out)
    if rig not in RIGS:
        raise ValueError(f"unknown rig {rig!r}; one of {RIGS}")
    if size < 16 or size % 8:
        raise ValueError(f"size must be a multiple of 8 and at least 16, got {size}")
    if lane not in LANES:
        raise ValueError(f"lane must be one of {LANES}, got {lane!r}")
    if scene not in SCENES:
        raise ValueError(f"scene must be one of {SCENES}, got {scene!r}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    effects = check_effects(effects)
    ranges = split_frames(frames)
    n_trajectory = ranges["test"][1]
    world = make_scene_world(scene, seed)
    poses, agents = make_scene_motion(world, n_trajectory, seed, lane, traffic)
    jobs = split_jobs(ranges, poses)

    tmp = temporary_folder(out)
    with sigterm_raises(), partial_folder(tmp, out):
        initargs = (
            *(FrameRenderer, tmp, seed, rig, size, supersample, lidar, scene, random_cameras),
            *(traffic, effects, lane, n_trajectory),
        )
        worker = initargs[0](*initargs[1:])
        masks = {name: r.body_mask for name, r in worker.cameras.items()}
        write_layout(tmp, worker.rig, masks, jobs, lidar, agents.n_agents > 0)
        desc = f"rendering {rig} {size}px" if scene == "street" else f"rendering {scene} {rig} {size}px"
        with tqdm(total=len(jobs), desc=desc, unit="frame", disable=not progress) as bar:
            render_jobs(jobs, worker, workers, initargs, bar)
        params = {
            "seed": seed,
            "rig": rig,
            "size": size,
            "supersample": supersample,
            "frames": frames,
            "lane": lane,
            "scene": scene,
            "random_cameras": random_cameras,
            "traffic": traffic,
            "effects": list(effects),
        }
        finish(tmp, out, metadata(worker.rig, world, ranges, params, lidar, agents))
    return out


def ensure_dataset(
    root: str | os.PathLike,
    rig: str = "kitti360",
    frames: int = 200,
    size: int = 256,
    seed: int = 0,
    supersample: int = 2,
    workers: int = 0,
    lidar: bool = True,
    progress: bool = True,
    lane: str = "right",
    scene: str = "street",
    random_cameras: bool = False,
    traffic: float = 0.0,
    effects=(),
) -> Path:
    """The synthetic dataset at ``root``, rendered on first use (what ``train.py`` calls). Returns ``root``.

    A finished dataset is used as it is, if it was rendered with the same rig, frames, size, seed,
    supersample, lane, scene, camera randomisation, traffic and effects (``DatasetMismatch``
    otherwise). An absent or empty ``root`` is rendered; a folder that this generator started but that
    has no ``synthetic.json`` is rendered again. Anything else raises ``NotASyntheticDataset`` (a
    ``FileExistsError``) and is left untouched.
    """
    check_options(locals(), GENERATE_OPTIONS)
    root = Path(root)
    asked = {
        "rig": rig,
        "frames": frames,
        "size": size,
        "seed": seed,
        "supersample": supersample,
        "lane": lane,
        "scene": scene,
        "random_cameras": random_cameras,
        "traffic": traffic,
        "effects": list(check_effects(effects)),
    }
    if is_complete(root):
        check_parameters(root, asked)
        return root
    if root.exists() and not is_empty_dir(root) and not made_by_generator(root):
        raise refusal(root)
    return generate(
        root,
        rig,
        frames,
        size,
        seed,
        supersample,
        workers,
        lidar,
        overwrite=root.exists(),
        progress=progress,
        lane=lane,
        scene=scene,
        random_cameras=random_cameras,
        traffic=traffic,
        effects=effects,
    )


def ensure_datasets(root, generate: dict, log=None) -> list[Path]:
    """:func:`ensure_dataset` for a data config: ``root`` one folder, or a list of folders (a mixed
    dataset); ``generate`` the config's ``data.generate`` mapping. With a list, ``generate["worlds"]``
    holds one mapping per folder, in the same order, whose keys replace the shared ones (``scene``,
    ``seed``, ...). Each folder is rendered on first use like a single one (its own progress bar, its own
    temporary folder renamed into place when complete). ``log``: a logger that names each folder it
    renders. Returns the folders. A parameter of the wrong kind or range is named as configured
    (``data.generate.traffic``), before anything is rendered."""
    check_options(generate, GENERATE_OPTIONS, "data.generate.")
    shared = {k: v for k, v in dict(generate).items() if k != "worlds"}
    worlds = generate.get("worlds")
    if isinstance(root, str | os.PathLike):
        if worlds:
            raise ValueError(
                "data.generate.worlds: one mapping per folder needs data.datamodule.root as a list"
            )
        jobs = [(Path(root), shared)]
    else:
        roots = [Path(r) for r in root]
        if not worlds or len(worlds) != len(roots):
            raise ValueError(
                f"data.datamodule.root lists {len(roots)} folders, so data.generate.worlds needs one mapping "
                f"per folder, in the same order; it has {len(worlds or [])}"
            )
        if len(set(roots)) != len(roots):
            raise ValueError(f"data.datamodule.root names a folder twice: {[str(r) for r in roots]}")
        jobs = [(r, {**shared, **dict(w)}) for r, w in zip(roots, worlds, strict=True)]
    for folder, params in jobs:
        if log is not None and not is_complete(folder):
            log.info("rendering the synthetic dataset into %s (first use)", folder)
        ensure_dataset(folder, **params)
    return [folder for folder, _ in jobs]
