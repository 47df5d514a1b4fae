"""What one bag import is asked to do (:class:`BagImport`), checked when it is made."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...files import path_name


@dataclass(frozen=True)
class BagImport:
    """One import of ``bag`` (:func:`~.importer.import_rosbag` says what each option does). ``cameras``:
    name -> image topic; ``info_topics``: name -> CameraInfo topic, filled where not given with the
    image topic's namespace + ``/camera_info`` (image_transport's layout); ``calibrations`` and
    ``extrinsics`` (4x4 camera -> body) given per camera instead of the bag's; poses from ``odometry``
    (a topic) or ``tf_poses`` (world frame, body frame), exactly one."""

    bag: Path
    cameras: Mapping[str, str]
    info_topics: Mapping[str, str] = field(default_factory=dict)
    calibrations: Mapping[str, str | os.PathLike] = field(default_factory=dict)
    extrinsics: Mapping[str, Any] = field(default_factory=dict)
    odometry: str | None = None
    tf_poses: tuple[str, str] | None = None
    body_frame: str | None = None
    sequence: str = "seq0"
    max_pose_gap: float | None = None
    bit_depth: int | None = None
    strict: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "bag", Path(self.bag))
        if (self.odometry is None) == (self.tf_poses is None):
            raise ValueError("poses: give exactly one of odometry=TOPIC or tf_poses=(WORLD, BODY)")
        if self.bit_depth is not None and not 8 <= self.bit_depth <= 16:
            raise ValueError(f"bit_depth: expected 8 to 16 bits, got {self.bit_depth}")
        if self.max_pose_gap is not None and not self.max_pose_gap > 0:
            raise ValueError(f"max_pose_gap: expected seconds > 0, got {self.max_pose_gap}")
        path_name(self.sequence, "sequence", "--sequence")  # each becomes a folder or file name under out
        for name in self.cameras:
            path_name(name, "camera", "--camera")
        info = dict(self.info_topics or {})
        for name, topic in self.cameras.items():  # image_transport: <ns>/image_raw[/compressed]
            info.setdefault(name, topic.removesuffix("/compressed").rsplit("/", 1)[0] + "/camera_info")
        object.__setattr__(self, "info_topics", info)
        object.__setattr__(self, "calibrations", dict(self.calibrations or {}))
        object.__setattr__(self, "extrinsics", dict(self.extrinsics or {}))

    @property
    def pose_source(self) -> str:
        """Where the poses come from, as messages name it."""
        return self.odometry or f"/tf {self.tf_poses[0]} -> {self.tf_poses[1]}"
