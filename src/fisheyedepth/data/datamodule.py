"""``FisheyeDataModule``: all configured cameras of a KITTI-360 or robot-rig dataset, sampled jointly;
or of several datasets at once (a list of roots: a mixed dataset)."""

from __future__ import annotations

import os
import random
from collections.abc import Iterator
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import ConcatDataset, DataLoader, Sampler

from ..models.depth_net import scale_focal
from ..options.kinds import check_options
from ..options.tables import DATAMODULE_OPTIONS
from .augment import Augment, PoseNoise
from .batch import collate
from .dataset import FisheyeDataset
from .kitti360 import OCCLUSION, Kitti360Layout
from .layouts import RigLayout

LAYOUTS = {"kitti360": Kitti360Layout, "rig": RigLayout}


class RootBatchSampler(Sampler[list[int]]):
    """Batches of a :class:`~torch.utils.data.ConcatDataset` that each come from one of its datasets (for
    datasets whose images cannot share a batch: different sizes, and no training size to resize them to);
    shuffled, the batches of all datasets are interleaved in a random order drawn from ``generator``."""

    def __init__(self, lengths: list[int], batch_size: int, shuffle: bool, drop_last: bool, generator=None):
        self.lengths, self.batch_size = list(lengths), batch_size
        self.shuffle, self.drop_last, self.generator = shuffle, drop_last, generator

    def _batches(self) -> list[list[int]]:
        batches, start = [], 0
        for n in self.lengths:
            order = torch.randperm(n, generator=self.generator).tolist() if self.shuffle else list(range(n))
            for i in range(0, n, self.batch_size):
                chunk = order[i : i + self.batch_size]
                if len(chunk) == self.batch_size or not self.drop_last:
                    batches.append([start + j for j in chunk])
            start += n
        if self.shuffle:
            batches = [batches[i] for i in torch.randperm(len(batches), generator=self.generator).tolist()]
        return batches

    def __iter__(self) -> Iterator[list[int]]:
        yield from self._batches()

    def __len__(self) -> int:
        full = sum(n // self.batch_size for n in self.lengths)
        return full if self.drop_last else sum(-(-n // self.batch_size) for n in self.lengths)


def seed_worker(worker_id: int) -> None:
    """Deterministic per-worker seeding: numpy and ``random`` follow torch's per-worker seed."""
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)  # noqa: NPY002  (seeds the legacy global state third-party code may draw from)
    random.seed(seed)


class FisheyeDataModule(L.LightningDataModule):
    """Every sample carries its own camera model, extrinsic-derived relative poses and body mask; a batch
    mixes cameras (and camera models) freely.

    Args:
        root: dataset folder; or a list of folders of one layout (a mixed dataset, e.g. synthetic worlds
            of several scenes and cameras): every split is the concatenation of each folder's split,
            ``base_focal`` the mean over the training cameras of all of them. A batch mixes samples of
            every folder when they share one image size (``size`` set, or equal native sizes); otherwise
            each batch comes from one folder (:class:`RootBatchSampler`).
        layout: "kitti360" (also the synthetic world) or "rig".
        splits: ``{"train": spec, "val": spec, "test": spec}``, each a split file, a list of
            ``{sequence, start, stop, stride, cameras}`` entries, or "all" (see ``parse_split``).
        size: training resolution ``(width, height)``; None keeps the native size.
        augment: training augmentation (flip and colour jitter); None disables it.
        ground_truth: "auto", "distance", "lidar" or "none", for the splits in ``ground_truth_splits``
            only (the scored ones; by default not train, where nothing reads it). LiDAR is projected
            lazily per frame and cached on disk; ``lidar_occlusion``: its occlusion filter (None: off).
        offsets: source frames of a training target (``scoring_loader`` reads none).
        rig_offsets: the rig's other cameras as sources too, at these time offsets (cross-camera
            consistency; empty: none; see ``FisheyeDataset``).
        pose_noise: ``{rotation_deg, translation, seed}`` seeded odometry error on the relative poses.
        max_pose_gap: seconds (rig layout): images in a longer gap of the poses are left out, never
            interpolated across it; None: ``rig.yaml``'s ``max_pose_gap``, else 5 median pose intervals.
        source_baseline: metres: each offset's source is the frame on its side nearest to this distance
            (scaled by ``|offset| / max|offsets|``) instead of a fixed frame offset; None: off.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        layout: str = "kitti360",
        splits: dict[str, Any] | None = None,
        cameras: list[str] | None = None,
        masks: dict[str, str] | None = None,
        size: tuple[int, int] | None = None,
        offsets: tuple[int, ...] = (-1, 1),
        min_translation: float = 0.03,
        max_translation: float = 3.0,
        augment: Augment | dict | None = None,
        ground_truth: str = "auto",
        skip_bad_frames: bool = False,
        batch_size: int = 8,
        num_workers: int = 0,
        pin_memory: bool = False,
        cache_dir: str | os.PathLike | None = None,
        seed: int = 0,
        pose_noise: PoseNoise | dict | None = None,
        ground_truth_splits: tuple[str, ...] | list[str] = ("val", "test"),
        lidar_occlusion: float | None = OCCLUSION,
        rig_offsets: tuple[int, ...] = (),
        source_baseline: float | None = None,
        max_pose_gap: float | None = None,
    ):
        given = locals()  # its arguments; an Augment or PoseNoise made already is its own, not a mapping
        check_options(
            {k: v for k, v in given.items() if not isinstance(v, Augment | PoseNoise)}, DATAMODULE_OPTIONS
        )
        super().__init__()
        if max_pose_gap is not None and layout != "rig":
            raise ValueError(f"max_pose_gap: only the rig layout interpolates poses, not {layout!r}")
        self.max_pose_gap = max_pose_gap
        self.rig_offsets, self.source_baseline = tuple(rig_offsets), source_baseline
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; one of {sorted(LAYOUTS)}")
        self.root, self.layout_name, self.cameras, self.masks = root, layout, cameras, masks
        single = isinstance(root, str | os.PathLike)
        self.roots = [root] if single else list(root)
        if not self.roots:
            raise ValueError("root: an empty list of dataset folders")
        self.splits = splits or {
            "train": "splits/train.txt",
            "val": "splits/val.txt",
            "test": "splits/test.txt",
        }
        self.size = tuple(size) if size is not None else None
        self.offsets, self.min_translation, self.max_translation = (
            tuple(offsets),
            min_translation,
            max_translation,
        )
        self.augment = Augment(**augment) if isinstance(augment, dict) else augment
        self.ground_truth, self.skip_bad_frames = ground_truth, skip_bad_frames
        self.ground_truth_splits, self.lidar_occlusion = tuple(ground_truth_splits), lidar_occlusion
        self.batch_size, self.num_workers, self.pin_memory = batch_size, num_workers, pin_memory
        self.cache_dir, self.seed = cache_dir, seed
        self.pose_noise = PoseNoise(**pose_noise) if isinstance(pose_noise, dict) else pose_noise
        self.datasets: dict[str, FisheyeDataset | ConcatDataset] = {}
        self._layouts: list | None = None

    @property
    def layouts(self) -> list:
        """One layout per root, in the order of ``root``."""
        if self._layouts is None:
            gap = {} if self.max_pose_gap is None else {"max_pose_gap": self.max_pose_gap}
            self._layouts = [
                LAYOUTS[self.layout_name](r, self.cameras, self.masks, **gap) for r in self.roots
            ]
        return self._layouts

    @property
    def layout(self):
        """The layout of ``root`` (of its first folder when it is a list)."""
        return self.layouts[0]

    def dataset(self, split: str) -> FisheyeDataset | ConcatDataset:
        """The ``split`` of ``root``; with a list of roots, the concatenation of each one's (in order)."""
        if split not in self.datasets:
            if split not in self.splits:
                raise KeyError(f"no {split!r} split configured (have {sorted(self.splits)})")
            parts = [self._dataset(layout, split) for layout in self.layouts]
            self.datasets[split] = parts[0] if len(self.roots) == 1 else ConcatDataset(parts)
        return self.datasets[split]

    def parts(self, split: str) -> list[FisheyeDataset]:
        """The ``split``'s dataset of each root, in the order of ``root``."""
        dataset = self.dataset(split)
        return list(dataset.datasets) if isinstance(dataset, ConcatDataset) else [dataset]

    def _dataset(self, layout, split: str) -> FisheyeDataset:
        return FisheyeDataset(
            layout,
            self.splits[split],
            self.cameras,
            self.size,
            self.offsets,
            self.min_translation,
            self.max_translation,
            self.augment if split == "train" else None,
            self.ground_truth if split in self.ground_truth_splits else "none",
            self.skip_bad_frames,
            self.cache_dir,
            lidar_occlusion=self.lidar_occlusion,
            pose_noise=self.pose_noise,
            rig_offsets=self.rig_offsets,
            source_baseline=self.source_baseline,
        )

    def base_focal(self, split: str = "train") -> float:
        """The mean :func:`~fisheyedepth.models.depth_net.scale_focal` (pixels) of the cameras that
        ``split`` samples, at the training size: ``base_focal: auto``. A camera with this focal gets
        ``depth_scale`` 1; one with a longer focal sees objects larger and gets a larger scale."""
        focals = []
        for layout, dataset in zip(self.layouts, self.parts(split), strict=True):
            for name in sorted({item.camera for item in dataset.items}):
                camera = layout.cameras[name].camera
                if self.size is not None:
                    camera = camera.resize(*self.size)
                focals.append(scale_focal(camera))
        if not focals:
            raise ValueError(f"{self.root}: the {split!r} split has no samples, so no base focal")
        return float(sum(focals) / len(focals))

    def setup(self, stage: str | None = None) -> None:
        wanted = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), "predict": ("test",)}
        for split in wanted.get(stage, tuple(self.splits)):
            if split in self.splits:
                self.dataset(split)

    def _one_size(self) -> bool:
        """Whether every sample of every root has one image size (so any of them may share a batch)."""
        if self.size is not None or len(self.roots) == 1:
            return True
        sizes = {
            (s.camera.width, s.camera.height) for layout in self.layouts for s in layout.cameras.values()
        }
        return len(sizes) == 1

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        generator = torch.Generator().manual_seed(self.seed)
        dataset = self.dataset(split)
        drop_last = shuffle and len(dataset) > self.batch_size
        if self._one_size():
            batching = dict(batch_size=self.batch_size, shuffle=shuffle, drop_last=drop_last)
        else:  # each batch from one root: images of one size
            sizes = [len(d) for d in self.parts(split)]
            sampler = RootBatchSampler(sizes, self.batch_size, shuffle, drop_last, generator=generator)
            batching = dict(batch_sampler=sampler)
        return DataLoader(
            dataset,
            **batching,
            num_workers=self.num_workers,
            collate_fn=collate,
            pin_memory=self.pin_memory,
            worker_init_fn=seed_worker,
            generator=generator,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self.dataloader("test")

    def dataloader(self, split: str) -> DataLoader:
        """Any configured split in order, unshuffled, by the training rules (neighbours, translation
        bounds, filtered LiDAR); evaluation reads :meth:`scoring_loader` instead."""
        return self._loader(split, shuffle=False)

    def scoring_loader(
        self,
        split: str,
        batch_size: int = 4,
        num_workers: int = 0,
        offsets: tuple[int, ...] = (),
        rig_offsets: tuple[int, ...] = (),
    ) -> DataLoader:
        """What evaluation scores: every frame of ``split`` (no source frames, hence no neighbour
        needed and no translation bound, as the reference scores its test set) at its native
        resolution, un-augmented, with ground truth (LiDAR unfiltered: each protocol filters its own).
        A multi-view network reads its sources: ``offsets`` and ``rig_offsets`` as in training, and then
        only the frames that have them are scored."""
        if split not in self.splits:
            raise KeyError(f"no {split!r} split configured (have {sorted(self.splits)})")
        parts = [
            FisheyeDataset(
                layout,
                self.splits[split],
                self.cameras,
                offsets=tuple(offsets),
                ground_truth=self.ground_truth,
                skip_bad_frames=self.skip_bad_frames,
                cache_dir=self.cache_dir,
                lidar_occlusion=None,
                rig_offsets=tuple(rig_offsets),
            )
            for layout in self.layouts
        ]
        if len(parts) == 1:
            return DataLoader(parts[0], batch_size, num_workers=num_workers, collate_fn=collate)
        sizes = {
            (s.camera.width, s.camera.height) for layout in self.layouts for s in layout.cameras.values()
        }
        if len(sizes) == 1:  # native sizes: one size, any samples may share a batch
            return DataLoader(ConcatDataset(parts), batch_size, num_workers=num_workers, collate_fn=collate)
        sampler = RootBatchSampler([len(p) for p in parts], batch_size, shuffle=False, drop_last=False)
        return DataLoader(
            ConcatDataset(parts), batch_sampler=sampler, num_workers=num_workers, collate_fn=collate
        )

    def predict_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)
