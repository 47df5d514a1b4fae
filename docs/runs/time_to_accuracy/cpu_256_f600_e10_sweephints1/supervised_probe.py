"""Diagnostic: can the network fit the kerb side's trunks when told the truth? Train cpu_30min's
network from scratch on world 0's training frames with |log L - log L*| against the rendered
distance (scale 0 only; no photometric term), N steps, then save a checkpoint.

    python supervised_probe.py REFERENCE_CKPT (for its hyper-parameters) WORLD0_ROOT STEPS OUT_CKPT
        [--decay-step K] [--augment] [--split splits/train.txt]

Session 19 added the options: ``--decay-step`` drops the learning rate tenfold at step K (as
cpu_30min's does after its 8th of 10 epochs), ``--augment`` applies the training's augmentation (flip
and colour jitter, Monodepth2's ranges), ``--split`` trains on another list of frames.
"""

import argparse
import tempfile
import time

import torch

from fisheyedepth.checkpoints import module_arguments
from fisheyedepth.data import Augment, FisheyeDataset, Kitti360Layout, collate
from fisheyedepth.module import FisheyeDepthModule

parser = argparse.ArgumentParser()
parser.add_argument("reference")
parser.add_argument("root")
parser.add_argument("steps", type=int)
parser.add_argument("out")
parser.add_argument("--decay-step", type=int)
parser.add_argument("--augment", action="store_true")
parser.add_argument("--split", default="splits/train.txt")
args = parser.parse_args()

torch.manual_seed(0)
torch.set_num_threads(2)
ref = torch.load(args.reference, weights_only=True, map_location="cpu")
hp = module_arguments(args.reference, ref)
module = FisheyeDepthModule(**hp).train()
steps = args.steps
ds = FisheyeDataset(
    Kitti360Layout(args.root),
    args.split,
    size=(256, 256),
    offsets=(-2, 2),
    ground_truth="distance",
    cache_dir=tempfile.mkdtemp(),
    augment=Augment() if args.augment else None,
)
loader = torch.utils.data.DataLoader(
    ds, batch_size=4, shuffle=True, collate_fn=collate, num_workers=1, drop_last=True, persistent_workers=True
)
opt = torch.optim.Adam(module.depth_net.parameters(), 3e-4)
t0, step = time.time(), 0
while step < steps:
    for b in loader:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = module(b.image_aug, b.camera)
        d = out["distance"][0].float()
        gt = b.distance
        ok = (gt > 0) & (b.mask > 0.5)
        loss = (d.clamp_min(1e-3).log() - gt.clamp_min(1e-3).log()).abs()[ok].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step == args.decay_step:
            for group in opt.param_groups:
                group["lr"] *= 0.1
        if step % 50 == 0:
            print(step, f"{loss.item():.4f}", f"{time.time() - t0:.0f}s", flush=True)
        if step >= steps:
            break
torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, args.out)
