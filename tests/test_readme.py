"""README.md is the front door: short, its links lead somewhere, its calibration example loads, and every
Hydra command it shows composes on today's configs."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from fisheyedepth.cameras import KannalaBrandtCamera, load_camera
from fisheyedepth.cli import model_file_alias

from conftest import ROOT

README = (ROOT / "README.md").read_text()
ENTRY_POINTS = {"train.py": "train", "eval.py": "eval", "predict.py": "predict", "export.py": "export"}


def commands(text: str) -> list[tuple[str, list[str]]]:
    """``(config name, overrides)`` of every ``python <entry point>.py ...`` line of the text's code
    blocks, continuation lines joined, comments cut; a sweep (``-m a,b``) as its first job, an optional
    ``[key=a|b]`` as ``key=a``, ``model=FILE.onnx`` as the entry points read it."""
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    out = []
    for line in "\n".join(blocks).replace("\\\n", " ").splitlines():
        if not line.startswith("python "):
            continue
        words = shlex.split(line.split("#", 1)[0])
        if words[1] not in ENTRY_POINTS:
            continue
        overrides = []
        for word in words[2:]:
            if word.startswith("[") and word.endswith("]") and "=" in word:  # an optional override
                word = word[1:-1].split("|")[0]
            elif "=" in word and "[" not in word:  # a sweep's first value
                word = word.split(",")[0]
            if word != "-m":
                overrides.append(word)
        name = ENTRY_POINTS[words[1]]
        out.append((name, overrides if name == "train" else model_file_alias(overrides)))
    return out


def test_the_readme_is_short_and_undated():
    assert len(README.splitlines()) <= 200
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", README)  # no history: git holds it


def test_every_link_of_the_readme_leads_to_a_file():
    links = re.findall(r"\]\(([^)#]+)\)", README)
    assert len(links) > 10
    missing = [link for link in links if not (ROOT / link).exists()]
    assert not missing, missing


def test_the_readme_calibration_example_loads(tmp_path):
    block = re.search(r"```yaml\n(.*?)```", README, re.S).group(1)
    path = tmp_path / "front.yaml"
    path.write_text(block)
    camera = load_camera(path)
    assert isinstance(camera, KannalaBrandtCamera)
    assert (camera.width, camera.height) == (1280, 1024) and camera.fx == pytest.approx(350.1)
    assert camera.k1 == pytest.approx(0.012) and camera.cy == pytest.approx(511.8)


DOCS = README + "".join(
    (ROOT / "docs" / f"{d}.md").read_text() for d in ("training", "inference", "real-data")
)


@pytest.mark.parametrize("name, overrides", commands(DOCS), ids=[" ".join(o) or n for n, o in commands(DOCS)])
def test_every_hydra_command_of_the_readme_and_docs_composes(name, overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name=name, overrides=overrides)
    assert cfg is not None


def test_the_readme_shows_each_entry_point():
    assert {name for name, _ in commands(README)} == set(ENTRY_POINTS.values())
    assert len(commands(README)) >= 8


def test_the_docs_the_readme_left_are_linked_from_it():
    for doc in ("training", "inference", "real-data", "package", "data-format", "faults", "geometry"):
        assert f"(docs/{doc}.md)" in README
        assert Path(ROOT / "docs" / f"{doc}.md").is_file()


def benchmark_commands(text: str) -> list[tuple[str, list[str]]]:
    """``(config name, overrides)`` of BENCHMARKS.md's inline commands (``python train.py ...``,
    ``make train ARGS="..."``; a ``...`` placeholder left out) and of its tables' override cells."""
    out = []
    for command in re.findall(
        r"`((?:python (?:train|eval|predict|export)\.py|make train ARGS=\")[^`]*)`", text
    ):
        words = shlex.split(" ".join(command.split()))
        if words[0] == "make":
            out.append(("train", shlex.split(words[2].split("=", 1)[1])))
        else:
            name = ENTRY_POINTS[words[1]]
            overrides = [w for w in words[2:] if w != "..."]
            out.append((name, overrides if name == "train" else model_file_alias(overrides)))
    section = text.split("### What did not help", 1)[1]
    levers = next(part for part in section.split("\n\n") if part.startswith("| change |"))  # train.py's
    for cell in re.findall(r"^\| [^|\n]* \| `([^`|]+=[^`|]*)` \|", levers, re.M):
        if not cell.startswith("python "):
            out.append(("train", shlex.split(cell)))
    return out


BENCHMARK_COMMANDS = benchmark_commands((ROOT / "BENCHMARKS.md").read_text())


@pytest.mark.parametrize(
    "name, overrides", BENCHMARK_COMMANDS, ids=[" ".join(o) or n for n, o in BENCHMARK_COMMANDS]
)
def test_every_hydra_command_of_benchmarks_composes(name, overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name=name, overrides=overrides)
    assert cfg is not None


def test_benchmarks_commands_are_found():
    assert len(BENCHMARK_COMMANDS) >= 20
