"""Rendering a synthetic dataset in the KITTI-360 layout (see docs/data-format.md): :func:`generate`
renders a :class:`~.spec.WorldSpec` into a folder, :func:`ensure_dataset` is the first-use variant for
training that reuses a finished dataset rendered with the same spec and never replaces a folder this
generator did not make, :func:`ensure_datasets` does it for each folder of a data config.

The scene comes from :mod:`.scene`, the frames are rendered by :mod:`.pool`'s workers with
:mod:`.frames`' renderer, and written into :mod:`.folder`'s temporary folder in :mod:`.layout`'s layout.
"""

from __future__ import annotations

import os
from pathlib import Path

from tqdm import tqdm

from ..options.kinds import check_options
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
from .scene import make_scene_motion, make_scene_world, split_frames, split_jobs
from .spec import GENERATE_OPTIONS, RENDERING, WorldSpec, check_render_memory


def _check_rendering(spec: WorldSpec, workers: int, lidar: bool, progress: bool) -> None:
    """``spec`` a :class:`WorldSpec` and the rendering options of their kinds, named as arguments, and
    the memory they need within this machine's (:func:`~.spec.check_render_memory`)."""
    if not isinstance(spec, WorldSpec):
        raise TypeError(f"spec: {spec!r} is not a WorldSpec")
    check_options({"workers": workers, "lidar": lidar, "progress": progress}, GENERATE_OPTIONS)
    check_render_memory(spec.params() | {"workers": workers})


def generate(
    out: str | os.PathLike,
    spec: WorldSpec,
    *,
    workers: int = 0,
    lidar: bool = True,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Render ``spec.frames`` frames of every camera of ``spec.rig`` into ``out``. Returns ``out``.

    ``workers``: worker processes (0 or 1: render in this process). ``lidar``: write the Velodyne scans
    too. With traffic, ``data_2d_moving`` holds each frame's mask of pixels that see a moving agent.
    ``overwrite`` replaces whatever ``out`` holds once the new dataset is complete (the CLI's explicit
    ``--overwrite``); ``ensure_dataset`` is the careful variant that replaces only what this generator made.
    SIGTERM or Ctrl-C stops the workers, removes the temporary folder and re-raises (``Terminated``).
    """
    _check_rendering(spec, workers, lidar, progress)
    out = Path(out)
    if out.exists() and not is_empty_dir(out) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    ranges = split_frames(spec.frames)
    world = make_scene_world(spec.scene, spec.seed)
    poses, agents = make_scene_motion(world, ranges["test"][1], spec.seed, spec.lane, spec.traffic)
    jobs = split_jobs(ranges, poses)

    tmp = temporary_folder(out)
    with sigterm_raises(), partial_folder(tmp, out):
        worker = FrameRenderer(tmp, spec, lidar)
        masks = {name: r.body_mask for name, r in worker.cameras.items()}
        write_layout(tmp, worker.rig, masks, jobs, lidar, agents.n_agents > 0)
        what = spec.rig if spec.scene == "street" else f"{spec.scene} {spec.rig}"
        desc = f"rendering {what} {spec.size}px"
        with tqdm(total=len(jobs), desc=desc, unit="frame", disable=not progress) as bar:
            render_jobs(jobs, worker, workers, (FrameRenderer, tmp, spec, lidar), bar)
        finish(tmp, out, metadata(worker.rig, world, ranges, spec, lidar, agents))
    return out


def ensure_dataset(
    root: str | os.PathLike, spec: WorldSpec, *, workers: int = 0, lidar: bool = True, progress: bool = True
) -> Path:
    """The synthetic dataset of ``spec`` at ``root``, rendered on first use (what ``train.py`` calls).
    Returns ``root``.

    A finished dataset is used as it is, if it was rendered with the same spec (``DatasetMismatch``
    otherwise). An absent or empty ``root`` is rendered; a folder that this generator started but that
    has no ``synthetic.json`` is rendered again. Anything else raises ``NotASyntheticDataset`` (a
    ``FileExistsError``) and is left untouched.
    """
    _check_rendering(spec, workers, lidar, progress)
    root = Path(root)
    if is_complete(root):
        check_parameters(root, spec)
        return root
    if root.exists() and not is_empty_dir(root) and not made_by_generator(root):
        raise refusal(root)
    return generate(root, spec, workers=workers, lidar=lidar, overwrite=root.exists(), progress=progress)


def ensure_datasets(root, generate: dict, log=None) -> list[Path]:
    """:func:`ensure_dataset` for a data config: ``root`` one folder, or a list of folders (a mixed
    dataset); ``generate`` the config's ``data.generate`` mapping. With a list, ``generate["worlds"]``
    holds one mapping per folder, in the same order, whose keys replace the shared ones (``scene``,
    ``seed``, ...). Each folder is rendered on first use like a single one (its own progress bar, its own
    temporary folder renamed into place when complete). ``log``: a logger that names each folder it
    renders. Returns the folders. A parameter of the wrong kind or range is named as configured
    (``data.generate.traffic``), and every folder's spec is made, before anything is rendered."""
    check_options(generate, GENERATE_OPTIONS, "data.generate.")
    check_render_memory(generate, "data.generate.")
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
    specs = [WorldSpec.from_config(params) for _, params in jobs]
    for (folder, params), spec in zip(jobs, specs, strict=True):
        if log is not None and not is_complete(folder):
            log.info("rendering the synthetic dataset into %s (first use)", folder)
        ensure_dataset(folder, spec, **{k: params[k] for k in RENDERING if k in params})
    return [folder for folder, _ in jobs]
