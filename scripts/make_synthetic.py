#!/usr/bin/env python
"""Render a synthetic fisheye dataset (same as the ``fisheyedepth-synthetic`` console command).

python scripts/make_synthetic.py --out data/synthetic --rig kitti360 --frames 200 --size 256 --seed 0
"""

from fisheyedepth.data.synthetic.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
