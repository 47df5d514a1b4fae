"""Shared fixtures: reference cameras of every model and the real-data folder."""

from __future__ import annotations

import contextlib
import io
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from fisheyedepth.cameras import (
    DoubleSphereCamera,
    ExtendedUnifiedCamera,
    Fisheye624Camera,
    FovCamera,
    KannalaBrandtCamera,
    MeiCamera,
    OpenCVCamera,
    PinholeCamera,
    UnifiedCamera,
)
from fisheyedepth.cameras.presets import tumvi_double_sphere, tumvi_kannala_brandt
from fisheyedepth.data.kitti360 import KITTI360_MEI, kitti360_camera

ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config):
    """Under pytest-xdist (``make test`` runs one worker per core) each worker gets its share of the
    cores: torch's intra-op threads and those of the processes a test starts (OMP_NUM_THREADS). Two
    workers of two threads each on two cores run slower than one worker: their threads wait for each
    other."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        threads = max(1, (os.cpu_count() or 1) // int(workers))
        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)


KITTI_02 = KITTI360_MEI[2]
KITTI_03 = KITTI360_MEI[3]


def kitti02(tangential: bool = False) -> MeiCamera:
    return kitti360_camera(2, tangential)


def kitti03(tangential: bool = False) -> MeiCamera:
    return kitti360_camera(3, tangential)


ARIA_SIDE_LEFT = [  # aria_gen2_rig/calib_slam_fisheye624.json, "slam-side-left"
    244.78391135310176, 252.66232836491685, 256.6758625428585, 0.033700017499895374, -0.0356144764687204,
    0.05016276920856296, -0.06365513840303465, 0.024101530347748173, -0.0028219261779819558,
    -0.001007436351907263, -0.0013828990859600307, 0.0018403425685775804, 8.515338893522913e-05,
    0.0009721496384546848, 0.0002693679794197647,
]  # fmt: skip


def aria_fisheye624():
    return Fisheye624Camera.from_aria_params(ARIA_SIDE_LEFT, (512, 512))


def all_cameras() -> dict[str, object]:
    """One camera per model and regime, small enough for full-grid tests."""
    return {
        "mei_kitti02_384": kitti02().resize(384, 384),
        "mei_kitti03_tangential_384": kitti03(tangential=True).resize(384, 384),
        # xi < 1 and a radial distortion that folds back: the domain ends where g'(r) = 0
        "mei_xi_below_1": MeiCamera(
            width=320, height=240, xi=0.8, k1=-0.25, k2=0.02, gamma1=300.0, gamma2=302.0, u0=160.3, v0=119.6
        ),
        "kb_tumvi": tumvi_kannala_brandt(),
        # a KB fit whose polynomial folds before 180 degrees (Aria slam-left fit)
        "kb_aria": KannalaBrandtCamera(
            width=640,
            height=480,
            fx=241.00432,
            fy=240.98965,
            cx=316.88001,
            cy=236.94558,
            k1=-0.0225306,
            k2=0.0922766,
            k3=-0.0640892,
            k4=0.0113456,
        ),
        # Aria Gen2 slam-side-left, factory calibration (its radial polynomial folds at 107.5 degrees)
        "fisheye624_aria": aria_fisheye624(),
        # stronger tangential and thin-prism terms, and a radial polynomial that folds at 123 degrees
        "fisheye624_strong": Fisheye624Camera(
            width=400,
            height=360,
            fx=120.0,
            fy=121.5,
            cx=201.3,
            cy=178.6,
            k0=0.02,
            k1=-0.012,
            p0=0.004,
            p1=-0.003,
            s0=0.002,
            s1=-0.0004,
            s2=-0.0015,
            s3=0.0003,
        ),  # fmt: skip
        "ds_tumvi": tumvi_double_sphere(),
        "ds_alpha_below_half": DoubleSphereCamera(
            width=400, height=300, fx=150.0, fy=151.0, cx=200.2, cy=149.7, xi=0.3, alpha=0.4
        ),
        "pinhole": PinholeCamera(width=320, height=240, fx=200.0, fy=201.0, cx=159.5, cy=120.25),
        # a 195-degree fisheye (the left and right image edges at 97 degrees); the corners are past the rim
        "ucm_fisheye_640": UnifiedCamera(
            width=640, height=480, fx=184.5, fy=184.2, cx=319.6, cy=240.3, alpha=0.62
        ),
        # a 200-degree fisheye (the left and right image edges at 100 degrees)
        "eucm_fisheye_640": ExtendedUnifiedCamera(
            width=640, height=480, fx=197.5, fy=197.2, cx=320.4, cy=239.1, alpha=0.64, beta=1.1
        ),
        # a 165-degree wide lens; the image corners see 107 degrees
        "fov_wide_640": FovCamera(width=640, height=480, fx=230.0, fy=229.6, cx=321.2, cy=238.9, w=1.05),
        # ROS plumb_bob, a USB camera with moderate barrel distortion (D = k1 k2 p1 p2 k3): its radial
        # map folds at 60.8 degrees, well outside the image (its corners at 37 degrees)
        "opencv_plumb_bob_usb": OpenCVCamera(
            width=640, height=480, fx=612.3, fy=611.8, cx=318.2, cy=242.7,
            k1=-0.2924, k2=0.0899, p1=0.0011, p2=-0.0007, k3=-0.0122,
        ),
        # ROS rational_polynomial, a 120-degree wide-angle lens (an equidistant fit out to 70 degrees):
        # its radial map folds at 78.7 degrees (p1/p2 fold it at 78.0), beyond the corners' 71 degrees
        "opencv_rational_120": OpenCVCamera(
            width=640, height=400, fx=305.6, fy=305.9, cx=321.7, cy=198.4,
            k1=0.5746, k2=0.03616, p1=-0.0004, p2=0.0003, k3=-0.0002, k4=0.9069, k5=0.1427, k6=0.001078,
        ),
    }  # fmt: skip


@pytest.fixture(params=list(all_cameras()))
def camera(request):
    return all_cameras()[request.param]


def realdata_dir() -> Path:
    return Path(os.environ.get("FISHEYEDEPTH_REALDATA", ROOT.parent / "shared" / "realdata"))


@pytest.fixture
def realdata() -> Path:
    path = realdata_dir()
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (set FISHEYEDEPTH_REALDATA)")
    return path


TRAIN_SEQ = "2013_05_28_drive_0000_sync"


def load_script(name: str):
    """``scripts/<name>.py`` as a module (``bench/bench_fit``, ``research/error_bands``: a script in its
    folder of scripts/), to test its functions without a subprocess. Its folder is on ``sys.path`` while
    it loads, as when it runs, for the siblings it imports."""
    import importlib.util

    path = ROOT / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(path.stem, path)
    script = importlib.util.module_from_spec(spec)
    with script_folder(name):
        spec.loader.exec_module(script)
    return script


@contextlib.contextmanager
def script_folder(name: str):
    """``scripts/<name>.py``'s folder on ``sys.path`` (first) for the block, as Python puts it there
    for a script it runs: the scripts import their siblings as top-level modules; and ``scripts/``
    itself, where they find ``_compose`` (a script run anew puts it there through its own import of
    ``_benchmarks``, which a test process imports once, while a test's ``monkeypatch`` restores
    ``sys.path`` after it)."""
    folders = [str((ROOT / "scripts" / f"{name}.py").parent), str(ROOT / "scripts")]
    added = [folder for folder in folders if folder not in sys.path]
    for folder in reversed(added):
        sys.path.insert(0, folder)
    try:
        yield
    finally:
        for folder in added:
            sys.path.remove(folder)


def printed(script: str, argv: list[str]) -> str:
    """What ``scripts/<script>.py`` prints for ``argv`` (its ``main`` must return 0), run in this process:
    a script tested without a second interpreter's start (seconds each), its folder on ``sys.path`` as
    when it runs."""
    out = io.StringIO()
    with script_folder(script), contextlib.redirect_stdout(out):
        assert load_script(script).main(argv) == 0
    return out.getvalue()


def quaternion_xyzw(R: np.ndarray) -> list[float]:
    """A rotation matrix as a unit quaternion (x, y, z, w), through its axis-angle (any rotation)."""
    rvec = cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].reshape(3)
    angle = float(np.linalg.norm(rvec))
    axis = rvec / angle if angle > 0 else np.zeros(3)
    return [*(axis * np.sin(angle / 2)), float(np.cos(angle / 2))]


def _overrides(tree, prefix=""):
    """``a.b=value`` overrides from a nested mapping (lists as Hydra writes them)."""
    for key, value in tree.items():
        if isinstance(value, dict):
            yield from _overrides(value, f"{prefix}{key}.")
        else:
            text = "[" + ",".join(map(str, value)) + "]" if isinstance(value, list) else str(value)
            yield f"{prefix}{key}={text}"


# train.py overrides for smoke runs, read from conf/debug/tiny.yaml (what `+debug=tiny` applies): a
# 12-frame 64 px world rendered in-process, 64 px training. As a list, so a test can pick a subset.
TINY = list(_overrides(yaml.safe_load((ROOT / "conf" / "debug" / "tiny.yaml").read_text())))


def built_once(tmp_path_factory, name: str, build) -> Path:
    """``path``, made by ``build(path)`` (a file or a folder) once for the whole test session: under
    pytest-xdist the workers share one copy (the first to ask builds it while the others wait; none of
    them writes into it afterwards), instead of each worker building its own."""
    import fcntl

    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        path = tmp_path_factory.mktemp(name) / name
        build(path)
        return path
    shared = tmp_path_factory.getbasetemp().parent / "shared"  # the session's folder, above each worker's
    shared.mkdir(exist_ok=True)
    path, done = shared / name, shared / f"{name}.done"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.is_file():
            if path.is_dir():  # a worker that failed while building
                import shutil

                shutil.rmtree(path)
            path.unlink(missing_ok=True)
            build(path)
            done.touch()
    return path


@pytest.fixture(scope="session")
def kitti_data(tmp_path_factory):
    """A 256 x 256 kitti360 synthetic dataset (12 frames with LiDAR), rendered once per test session."""
    from fisheyedepth.synthetic import WorldSpec, generate

    def render(path: Path) -> None:
        generate(path, WorldSpec("kitti360", frames=12, size=256, seed=3), progress=False)

    return built_once(tmp_path_factory, "kitti", render)


def tiny_batch(root, frames=(2, 3), cameras=("image_02", "image_03"), size=(64, 64)):
    """A training batch read through ``FisheyeDataset``, resized to ``size`` (the camera models with it)."""
    from fisheyedepth.data import collate

    return collate(tiny_samples(root, frames, cameras, size))


def tiny_samples(root, frames=(2, 3), cameras=("image_02", "image_03"), size=(64, 64)):
    """The samples of :func:`tiny_batch`, one dict each, in the order frames x cameras."""
    import tempfile

    from fisheyedepth.data import FisheyeDataset, Kitti360Layout

    layout = Kitti360Layout(root)
    with tempfile.TemporaryDirectory(prefix="fd-cache-") as cache:  # removed once the samples are read
        dataset = FisheyeDataset(
            layout, [{"sequence": TRAIN_SEQ}], size=size, ground_truth="distance", cache_dir=cache
        )
        index = {(layout.frames(it.sequence)[it.row].key, it.camera): i for i, it in enumerate(dataset.items)}
        return [dataset[index[(f, c)]] for f in frames for c in cameras]


@pytest.fixture(scope="session")
def checkpoint(kitti_data, tmp_path_factory):
    """A full model trained for a handful of steps at 64x64, saved like Lightning saves it."""
    return built_once(
        tmp_path_factory, "tiny.ckpt", lambda path: train_few_steps(kitti_data, path)
    )  # base_focal as train.py's auto


def train_few_steps(kitti_data: Path, path: Path, **net) -> None:
    """A model (``net`` options over a 64x64 two-scale network) trained for three steps on the tiny
    KITTI-360 batch, saved to ``path`` like Lightning saves it."""
    import torch

    torch.manual_seed(0)
    module = bare_module(net={"scales": (0, 1), "base_focal": 20.0, **net}, input_size=(64, 64))
    batch = tiny_batch(kitti_data)
    opt = torch.optim.Adam(module.parameters(), 1e-3)
    for _ in range(3):
        loss, _ = module.objective(batch, module(batch.image, batch.camera, module.sources(batch)))
        opt.zero_grad()
        loss.backward()
        opt.step()
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, path)


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory) -> Path:
    """The world ``+debug=tiny`` trains on (12 frames at 64 px), rendered once per test session the way
    train.py renders it on first use (``prepare_data`` on the composed train config), instead of once in
    every module that trains a tiny run; a test that needs it under its own ``paths.data_dir`` takes a
    copy (:func:`copy_tiny_world`)."""
    from hydra import compose, initialize_config_dir

    from fisheyedepth.cli import prepare_data
    from fisheyedepth.plan import data_plan

    def config(data_dir: Path):
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            return compose("train", [*TINY, f"paths.data_dir={data_dir}"])

    data_dir = built_once(tmp_path_factory, "tiny_world", lambda path: prepare_data(data_plan(config(path))))
    root = Path(config(data_dir).data.datamodule.root)
    assert (root / "synthetic.json").is_file(), root
    return root


def copy_tiny_world(tiny_world: Path, data_dir: Path) -> Path:
    """``data_dir`` (``paths.data_dir`` of a tiny run) holding its own copy of the tiny world, so that
    train.py finds it rendered; returns ``data_dir``."""
    import shutil

    data_dir.mkdir(parents=True, exist_ok=True)
    shutil.copytree(tiny_world, data_dir / tiny_world.name)
    return data_dir


def load_cfg(name: str, **values):
    """A command's config (``conf/<name>.yaml``) as Hydra would compose it (its own keys), without
    Hydra's runtime: for running a command's function in-process."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(ROOT / "conf" / f"{name}.yaml")
    for hydra_only in ("defaults", "hydra"):
        cfg.pop(hydra_only, None)
    return OmegaConf.merge(cfg, {k: str(v) if isinstance(v, Path) else v for k, v in values.items()})


# ---------------------------------------------------------------------------------------- small modules
# The unit tests' module: the YAML's options (fisheyedepth.options) with what a test on a few 64 px frames
# needs instead of the training recipe's: no depth scale (no training cameras resolve ``base_focal:
# auto``), nothing compiled, NCHW weights, the loss at the input size, sources one frame either side, and
# Monodepth2's learning rate and schedule. A test states any other option it depends on.
TEST_NET = {"base_focal": None, "channels_last": False}
TEST_OBJECTIVE = {"source_offsets": (-1, 1), "loss_resolution": "full"}
TEST_MODULE = {"compile_kernels": False, "optimizer": {"lr": 1e-4}, "scheduler": {"step_size": 8}}


def bare_net(**net):
    """A :class:`~fisheyedepth.models.DepthNet` with the YAML's options, :data:`TEST_NET` and ``net``."""
    from fisheyedepth.models import DepthNet
    from fisheyedepth.options.defaults import net_options

    return DepthNet(**net_options(**TEST_NET | net))


def bare_objective(**objective):
    """A :class:`~fisheyedepth.losses.objective.SelfSupervisedObjective` with the YAML's options,
    :data:`TEST_OBJECTIVE` and ``objective``."""
    from fisheyedepth.losses.objective import SelfSupervisedObjective
    from fisheyedepth.options.defaults import objective_options

    return SelfSupervisedObjective(**objective_options(**TEST_OBJECTIVE | objective))


def bare_options(**options) -> dict:
    """The module's keywords for a unit test: :data:`TEST_NET`, :data:`TEST_OBJECTIVE` and
    :data:`TEST_MODULE` under ``options`` (groups merged key by key)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in TEST_MODULE.items()}
    out["net"], out["objective"] = dict(TEST_NET), dict(TEST_OBJECTIVE)
    for key, value in options.items():
        merge = (
            isinstance(value, dict) and key in out and "_target_" not in value
        )  # a class of its own: as given
        out[key] = {**out[key], **value} if merge else value
    return out


def bare_module(**options):
    """A :class:`~fisheyedepth.module.FisheyeDepthModule` with :func:`bare_options`."""
    from fisheyedepth.module import FisheyeDepthModule

    return FisheyeDepthModule(**bare_options(**options))
