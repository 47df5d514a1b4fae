"""What the project computes, written back for a robot's tools, without a ROS install (``rosbags``):
ROS 2 messages of distance, confidence, cameras, points and poses (:mod:`.messages`), a ROS 2 bag or
MCAP file of them (:mod:`.bag`), and the same served live to Foxglove (:mod:`.foxglove`).
docs/inference.md ("ROS 2 bags and Foxglove") lists the topics and their conventions."""

from .bag import BagRecorder, BagWriter, check_bag_out

__all__ = ["BagRecorder", "BagWriter", "check_bag_out"]
