#!/usr/bin/env python
"""Import a ROS 1 or ROS 2 bag into the rig layout: the same as the console script
``fisheyedepth-import-rosbag`` (``--help`` for its options)."""

from fisheyedepth.data.rosbag import main

if __name__ == "__main__":
    raise SystemExit(main())
