"""The installed environment is the one the project promises."""

from __future__ import annotations

import importlib.util
import platform
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import fisheyedepth

ROOT = Path(__file__).resolve().parents[1]


def test_version_and_torch_pin():
    assert fisheyedepth.__version__
    assert torch.__version__.split("+")[0] == "2.13.0"


def test_constraints_pin_torch_and_block_torchvision():
    lines = {line.strip() for line in (ROOT / "constraints.txt").read_text().splitlines()}
    assert "torch==2.13.0" in lines
    assert "torchvision==0.0.0" in lines  # no such release: anything that wants torchvision fails to resolve
    assert importlib.util.find_spec("torchvision") is None


def test_lightning_imports():
    import lightning  # noqa: F401  (breaks when a CUDA-only torchvision is installed)


def test_configs_become_objects_only_in_the_commands():
    """``hydra.utils.instantiate`` lives in ``fisheyedepth.cli`` alone; every command is one small module
    there beside the run folder guard the commands share, and the console script points at one of them."""
    package = ROOT / "src" / "fisheyedepth"
    users = sorted(
        str(p.relative_to(package)) for p in package.rglob("*.py") if "instantiate(" in p.read_text()
    )
    assert users and all(u.startswith("cli/") for u in users), users
    commands = sorted(p.stem for p in (package / "cli").glob("*.py"))
    assert commands == [
        "__init__", "estimate_mask", "evaluate", "export", "import_aria", "import_ddad", "import_rosbag",
        "multiview", "predict", "run_folder", "synthetic", "train",
    ]  # fmt: skip
    small = [p for p in (package / "cli").glob("*.py") if p.stem != "run_folder"]  # the commands
    assert max(len(p.read_text().splitlines()) for p in small) < 150
    scripts = (ROOT / "pyproject.toml").read_text()
    assert 'fisheyedepth-predict = "fisheyedepth.cli.predict:main"' in scripts
    import subprocess
    import sys

    shown = subprocess.run(
        [sys.executable, "-c", "from fisheyedepth.cli.predict import main; main()", "--cfg", "job"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert shown.returncode == 0 and "task_name: predict" in shown.stdout, shown.stderr[-500:]


def test_commands_that_train_nothing_start_without_lightning():
    """Prediction, export, the synthetic generator (and its worker processes) import no Lightning, and
    train.py imports it only once its folder, checkpoint and data are found usable: importing it takes
    about 3 s of each such process's start on 2 cores."""
    code = (
        "import sys\n"
        "import fisheyedepth.cli.predict, fisheyedepth.cli.export, fisheyedepth.cli.synthetic\n"
        "import fisheyedepth.cli.train\n"
        "from fisheyedepth.runtimes import TrainedDepthNet\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('lightning', 'pytorch_lightning')))\n"
    )
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert shown.returncode == 0 and shown.stdout.strip() == "[]", shown.stdout[-500:] + shown.stderr[-500:]


def test_the_lightning_module_keeps_the_lifecycle_alone():
    """The objective (``losses/objective.py``), the step guard and the optimiser builders
    (``training.py``) and the option groups (``options/``) live apart from the LightningModule."""
    package = ROOT / "src" / "fisheyedepth"
    assert len((package / "module.py").read_text().splitlines()) <= 300
    for name in ("losses/objective.py", "training.py", "options/defaults.py"):
        assert (package / name).is_file(), name


FAULTS_OF_REPEATED_STEPS = """
import resource, sys
if sys.argv[1] == "keep":
    from fisheyedepth.utils import keep_freed_memory
    assert keep_freed_memory()
import torch
faults = []
for step in range(8):  # each "step" allocates and frees 40, 100 and 60 MB (above glibc's 32 MB mmap limit)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a, b = torch.ones(10_000_000), torch.ones(25_000_000)
    c = a[:1000] + 1
    d = torch.ones(15_000_000)
    del a, b, c, d
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[4:]))
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="keep_freed_memory is for glibc")
def test_keep_freed_memory_reuses_freed_blocks_instead_of_faulting_them_in_again():
    """By default glibc maps each large tensor afresh and unmaps it when freed: every step faults in
    all 200 MB again (one fault per 4 kB page, about 49,000 a step; 12,500 where the kernel maps anonymous
    memory in 16 kB folios). After ``keep_freed_memory`` the heap keeps freed blocks and reuses them: over
    four steps once warm, a small share of that."""
    faults = {}
    for kind in ("default", "keep"):
        out = subprocess.run(
            [sys.executable, "-c", FAULTS_OF_REPEATED_STEPS, kind], capture_output=True, text=True, check=True
        )
        faults[kind] = int(out.stdout.split()[-1])
    assert faults["default"] > 4 * 10_000, faults  # 200 MB a step, in pages of 16 kB at most
    assert faults["keep"] < faults["default"] / 4, faults


def test_the_package_map_shows_every_module_once():
    """docs/package.md's tree (one line a module) holds every module of ``src/fisheyedepth`` and no
    other, each under its own package."""
    root = Path(fisheyedepth.__file__).parent
    text = (ROOT / "docs" / "package.md").read_text()
    tree = text.split("## Layout", 1)[1].split("```text\n", 1)[1].split("```", 1)[0].splitlines()
    assert tree[0] == "fisheyedepth/"
    shown, above = [], []  # above: the packages the line lies in, outermost first
    for line in tree[1:]:
        depth = line.index("── ") // 4
        name = line[depth * 4 + 4 :].split()[0]
        del above[depth:]
        shown.append("".join(above) + name)
        if name.endswith("/"):
            above.append(name)
    files = [str(p.relative_to(root)) for p in root.rglob("*.py") if p.name != "__init__.py"]
    packages = [f"{p.parent.relative_to(root)}/" for p in root.rglob("__init__.py") if p.parent != root]
    assert sorted(shown) == sorted(files + packages)
    assert len(shown) == len(set(shown))
