"""ROS bags into the robot-rig layout (docs/data-format.md), with the pure-Python ``rosbags`` library:
what a bag's messages hold (:mod:`.messages`), what an import is asked (:mod:`.options`, :class:`BagImport`),
a first pass that indexes the bag and checks every camera (:mod:`.index`) and a second that writes the
images (:mod:`.write`), run by :func:`import_rosbag` (:mod:`.importer`).

``import_rosbag(bag, out, cameras={name: image_topic}, ...)`` reads a ROS 1 ``.bag`` or a ROS 2 bag (a
folder with ``metadata.yaml`` and sqlite3 ``.db3`` or ``.mcap`` files) and writes:

- ``<sequence>/images/<camera>/<stamp_ns>.png`` from ``sensor_msgs/Image`` (mono8, mono16, rgb8,
  bgr8, rgba8, bgra8) or ``sensor_msgs/CompressedImage``, stamped by their headers; 16-bit images are
  scaled from their bit depth (detected over the whole topic, or given) to the full 16-bit range;
- ``calibration/<camera>.yaml`` from the camera's ``sensor_msgs/CameraInfo`` (``plumb_bob`` with 5
  coefficients or ``rational_polynomial`` with 8 -> the ``opencv`` model, a pinhole with OpenCV's
  distortion; either without distortion -> pinhole; ``equidistant`` with 4 -> Kannala-Brandt; anything
  else is refused, naming the topic, the model and the coefficient count; see :func:`camera_from_info`)
  or from a calibration file the user gives;
- ``rig.yaml`` with each camera's ``cam_to_body`` from ``/tf_static`` (the chain from the body frame
  to the camera's ``frame_id``) or given;
- ``<sequence>/poses.txt`` from ``nav_msgs/Odometry`` (``--odometry``) or from ``/tf``
  (``--tf-poses WORLD BODY``, a direct edge). The rig layout interpolates them to each image's stamp;
  images outside the poses' time range, or in a gap of the poses longer than ``max_pose_gap``, are
  dropped here and counted, as the rig layout would drop them.

The import is written into a hidden folder beside ``out``, opened with ``RigLayout`` (what training
will read) and only then moved into place: a failed import leaves nothing at ``out``. A corrupt image
message is skipped and counted (refused with ``strict``). Nothing is overwritten without ``overwrite``.
Camera and sequence names become folder and file names under ``out``: each must be one plain name
(:func:`fisheyedepth.files.path_name`: no ``/``, no ``..``, ...).
"""

from .importer import import_rosbag, imported, is_bag
from .messages import CorruptMessage, RosbagError, camera_from_info, decode_image, rigid_pose
from .options import BagImport

__all__ = ["BagImport", "CorruptMessage", "RosbagError", "camera_from_info", "decode_image", "import_rosbag",
           "imported", "is_bag", "rigid_pose"]  # fmt: skip
