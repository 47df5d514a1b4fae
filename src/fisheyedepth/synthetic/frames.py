"""The renderer of a dataset's frames: built once per process from a :class:`~.spec.WorldSpec` (the
world, the rig's camera and LiDAR renderers, the traffic and each camera's sensor effects), it renders a
:class:`~.scene.Job` and writes its files (:mod:`.layout`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .layout import write_camera_frame, write_scan
from .raycast import Movers, scene_tensors
from .render import CameraRenderer, LidarRenderer, quantise
from .rig import make_rig
from .scene import Job, make_scene_motion, make_scene_world, pose_at, split_frames
from .sensor import Sensor, blur_times
from .spec import WorldSpec


class FrameRenderer:
    """Renders and writes whole frames into ``root``; built once per process."""

    def __init__(self, root: Path, spec: WorldSpec, lidar: bool):
        seed, scene = spec.seed, spec.scene
        self.root, self.world = root, make_scene_world(scene, seed)
        self.rig = make_rig(spec.rig, spec.size, scene, spec.random_cameras, seed)
        self.effects = spec.effects
        self.poses, self.traffic = None, None
        if spec.traffic or "motion_blur" in self.effects:  # the motion around each frame is needed
            frames = split_frames(spec.frames)["test"][1]
            self.poses, self.traffic = make_scene_motion(self.world, frames, seed, spec.lane, spec.traffic)
        # the street with its own cameras keeps the ground truth it has always had (SceneTensors)
        self.scene = scene_tensors(self.world, legacy_culling=scene == "street" and not spec.random_cameras)
        self.cameras = {
            name: CameraRenderer(cam, self.rig.cam_to_pose[name], spec.supersample, self.rig.ego)
            for name, cam in self.rig.cameras.items()
        }
        self.lidar = LidarRenderer(self.rig.velo_to_pose, ego=self.rig.ego) if lidar else None
        self.sensors = {}
        if self.effects:
            for i, (name, renderer) in enumerate(self.cameras.items()):
                valid = renderer.centre.untile(renderer.centre.valid[:, None])[..., 0].numpy()
                self.sensors[name] = Sensor(self.effects, seed, i, valid)

    def movers(self, time: float, pose: np.ndarray) -> Movers | None:
        """The traffic's boxes at a (fractional) trajectory frame; None without traffic."""
        if self.traffic is None or not self.traffic.n_agents:
            return None
        return Movers.from_boxes(self.traffic.boxes_at(time, pose[:2, 3]))

    def __call__(self, job: Job) -> None:
        movers = self.movers(job.index, job.pose)
        moving = self.traffic.moving(job.index) if movers is not None else None
        shots = [(job.pose, movers)]
        if "motion_blur" in self.effects:  # the open shutter: the car and the traffic move
            shots = [(pose := pose_at(self.poses, t), self.movers(t, pose)) for t in blur_times(job.index)]
        for name, renderer in self.cameras.items():
            colour = sum(renderer.colour(self.scene, self.world, *shot) for shot in shots) / len(shots)
            sensor = self.sensors.get(name)
            if sensor is not None:
                colour = sensor(colour, job.index)
            distance, moving_mask = renderer.truth(self.scene, job.pose, movers, moving)
            write_camera_frame(self.root, job, name, quantise(colour), distance, moving_mask)
        if self.lidar is not None:
            write_scan(self.root, job, self.lidar.render(self.scene, self.world, job.pose, movers))
