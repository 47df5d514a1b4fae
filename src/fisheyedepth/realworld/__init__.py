"""Scores on real photographs with metric ground truth, apart from everything trained or matched: the real
frames and their calibrations (:mod:`.frames`: KITTI-360 with LiDAR, ScanNet++, Aria Digital Twin, DDAD),
the real image pairs and their overlap (:mod:`.pairs`: the Aria Digital Twin SLAM pair, Middlebury
Motorcycle), a runtime scored on a frame under its protocols (:mod:`.scores`) and stereo scored on the
pairs (:mod:`.stereo`). Nothing here trains or tunes on what it scores."""
