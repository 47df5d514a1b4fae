#!/usr/bin/env python
"""Estimate a camera's vehicle-body mask from a recording and write it where the layout reads it: the
same as the console script ``fisheyedepth-estimate-mask`` (``--help`` for its options).

    python scripts/estimate_body_mask.py --root data/kitti360 --sequence 2013_05_28_drive_0000_sync \
        --camera image_02 [--frames 200] [--out PATH] [--threshold X] [--sky-elevation DEG] [--overwrite]
"""

from fisheyedepth.data.body_mask import main

if __name__ == "__main__":
    raise SystemExit(main())
