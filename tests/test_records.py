"""The kept run records (``docs/records``) stay small and complete, and every table BENCHMARKS.md
publishes from them is what its command prints from them today, cell for cell (nothing retrained)."""

from __future__ import annotations

import json
import re
import shlex
import sys
from pathlib import Path

import pytest

from conftest import load_script, printed

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "docs" / "records"
BENCHMARKS = (ROOT / "BENCHMARKS.md").read_text()
# a published table: <!-- table: NAME; python scripts/[FOLDER/]SCRIPT.py ARGS --> table lines <!-- /table -->
TABLE = re.compile(
    r"<!-- table: (?P<name>[\w-]+); (?P<command>[^\n]*?) -->\n(?P<body>.*?)<!-- /table -->", re.S
)
RECORD_FILES = sorted(RECORDS.rglob("*.json"))


@pytest.fixture(autouse=True)
def scripts_importable(monkeypatch):
    """The record-reading scripts import each other as top-level modules, as they do when run from their
    folder, scripts/research/."""
    monkeypatch.syspath_prepend(str(ROOT / "scripts" / "research"))
    monkeypatch.chdir(ROOT)


def table_rows(text: str) -> list[list[str]]:
    """The cells of every Markdown table line in ``text``, in order."""
    return [
        [c.strip() for c in line.strip().strip("|").split("|")]
        for line in text.splitlines()
        if line.startswith("|")
    ]


def test_the_records_are_small_json_files():
    assert len(RECORD_FILES) > 50
    files = [f for f in RECORDS.rglob("*") if f.is_file()]
    assert all(f.suffix == ".json" for f in files), [f for f in files if f.suffix != ".json"]
    assert sum(f.stat().st_size for f in files) < 2_500_000


@pytest.mark.parametrize("path", RECORD_FILES, ids=lambda p: str(p.relative_to(RECORDS)))
def test_every_record_has_overrides_final_metrics_and_curves_or_says_why_not(path):
    record = json.loads(path.read_text())
    assert record["format"] == 1 and record["name"] == str(path.relative_to(RECORDS).with_suffix(""))
    missing = set(record.get("not_recorded", []))
    for key in ("overrides", "results", "curves"):  # overrides [] is a run of the defaults (make train)
        assert key in record and (
            bool(record[key]) or record[key] == [] == record["overrides"] or key in missing
        ), key
    assert missing <= {"overrides", "results", "curves"}
    if record["overrides"] is not None:
        assert all(isinstance(o, str) and ("=" in o or o.startswith("~")) for o in record["overrides"])
    for results in [record["results"], *record["heldout"].values()]:
        if results is not None:
            assert {"abs_rel", "a1"} <= set(results["results"]["full"]["none"])
            assert {"abs_rel", "a1"} <= set(results["results"]["kitti360"]["none"])
    curves = record["curves"]
    if curves:  # one value per epoch (None where a column has none), epochs in order
        epochs = curves["epoch"]
        assert epochs == sorted(set(epochs)) and "val/loss" in curves
        assert all(len(v) == len(epochs) for v in curves.values())


def published_tables() -> list:
    return [
        pytest.param(m["name"], m["command"], m["body"], id=m["name"]) for m in TABLE.finditer(BENCHMARKS)
    ]


def test_benchmarks_publishes_marked_tables_with_their_commands():
    names = [table.values[0] for table in published_tables()]
    assert len(names) == len(set(names)) >= 3, names
    opening = re.findall(r"^<!-- table:", BENCHMARKS, re.M)
    assert len(opening) == len(re.findall(r"^<!-- /table -->$", BENCHMARKS, re.M)) == len(names)


@pytest.mark.parametrize("name, command, body", published_tables())
def test_a_published_table_is_what_its_command_prints_from_the_records(name, command, body):
    words = shlex.split(command)
    scripts = ("research/make_tables.py", "research/heldout.py", "tools/real_world.py")
    assert words[0] == "python" and words[1] in [f"scripts/{s}" for s in scripts], command
    if not words[1].endswith("make_tables.py"):
        assert "--from-records" in words  # never re-scored here
    assert any(w.startswith("docs/records") for w in words[2:]), "tables are built from the records"
    expected = table_rows(printed(str(Path(words[1]).relative_to("scripts").with_suffix("")), words[2:]))
    assert table_rows(body) == expected, name


def test_the_reproduce_section_is_what_reproduce_prints_from_the_records():
    """The Tables 1 and 2 block (scripts/research/reproduce.py writes it between its markers): its tables,
    the budget overrides and the tested checkpoints, rebuilt from the records it names."""
    block = BENCHMARKS.split("<!-- reproduce:start -->", 1)[1].split("<!-- reproduce:end -->", 1)[0]
    command = re.search(
        r"Command: `python scripts/research/reproduce.py --runs (\S+) --tables ([\d ]+)`", block
    )
    assert command and command[1].startswith("docs/records/")
    sources, tables = [command[1]], command[2].split()
    expected = []
    for protocol in ("full", "kitti360"):
        expected += table_rows(
            printed("research/make_tables", [*sources, "--tables", *tables, "--protocol", protocol])
        )
    assert table_rows(block) == expected
    reproduce = load_script("research/reproduce")
    assert f"Budget overrides of every run: `{' '.join(reproduce._shared_overrides(sources))}`." in block
    assert f"Tested checkpoints (selected without ground truth): {reproduce._tested(sources)}." in block


def test_the_record_reading_scripts_agree_with_the_records():
    """make_tables' --heldout and heldout.py's --from-records read the same held-out scores."""
    record_file = RECORDS / "table2_world34_e20" / "ablation_full_s0.json"
    record = json.loads(record_file.read_text())
    held = record["heldout"]["heldout_kitti360_seed1001"]["results"]
    row = table_rows(printed("research/heldout", ["--from-records", str(record_file), "--seeds", "1001"]))[-1]
    assert row == [
        "ablation_full_s0",
        load_script("research/heldout").formatted(record["results"]["results"]),
        f"{held['full']['none']['abs_rel']:.3f}, {held['full']['none']['a1']:.3f} / "
        f"{held['kitti360']['none']['abs_rel']:.3f}",
    ]
    assert sys.modules.get("make_tables") is not None  # heldout.py read the records through it
