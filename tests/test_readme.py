"""``visland readme``: the README's demo picture and output block come from a real demo run of
the shipped model, and a test fails the day they name another model.

The end-to-end test flies one landing (~10 s: the demo's cheap path; ``make readme`` flies the
default three) into a copy of README.md in a tmp folder and checks the block against the run's
own records: ``demo.json`` and the SITL's ``/episode/result`` in each flight log.
"""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from companion.files import sha256_file
from companion.flightlog import read_log
from tools.readme import (
    OUTPUT_REGION,
    PICTURE_REGION,
    ModelIdentity,
    ReadmeConfig,
    ReadmeError,
    model_identity,
    region,
    run,
)
from training.provenance import REPO, SHIPPED_MODEL

README = REPO / "README.md"


def _outside(text: str) -> str:
    """``text`` with both generated regions blanked (what the command must leave alone)."""
    for name in (PICTURE_REGION, OUTPUT_REGION):
        text = text.replace(region(text, name), "")
    return re.sub(r"<!-- (demo-\w+):start[^\n]*-->", r"<!-- \1:start -->", text)


def test_the_readme_names_the_shipped_model():
    """The README's demo output was generated from the model in ``models/``: after a new
    ``visland ship``, run ``make readme`` (this test says so until then)."""
    text = README.read_text()
    recorded = model_identity(text, str(README))
    shipped = ModelIdentity(SHIPPED_MODEL.relative_to(REPO).as_posix(), sha256_file(SHIPPED_MODEL))
    assert recorded == shipped, (
        f"README.md shows the demo of {recorded}, the shipped model is {shipped}: run `make readme`"
    )
    picture = re.search(r"!\[[^\]]*\]\(([^)]+)\)", region(text, PICTURE_REGION))
    assert picture is not None and (REPO / picture[1]).is_file()
    block = region(text, OUTPUT_REGION)
    assert "$ visland demo\n" in block  # the default three landings, not a shortened run
    assert block.count(" success") + block.count(" FAILED") >= 3


@pytest.fixture(scope="module")
def rewritten(tmp_path_factory) -> tuple[Path, Path, str]:
    """``visland readme --episodes 1`` run as a user runs it on a copy of README.md: the tmp
    folder, the demo's output folder and the README copy's text before the run."""
    tmp = tmp_path_factory.mktemp("readme")
    before = README.read_text()
    (tmp / "README.md").write_text(before)
    demo = tmp / "demo"
    args = ["--readme", tmp / "README.md", "--picture", tmp / "docs" / "demo.png", "--out", demo]
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "readme", "--episodes", "1", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return tmp, demo, before


def test_readme_command_writes_the_runs_landing_errors_into_a_copy(rewritten):
    tmp, demo, before = rewritten
    text = (tmp / "README.md").read_text()
    assert _outside(text) == _outside(before)  # nothing outside the markers changed
    report = json.loads((demo / "demo.json").read_text())
    assert report["episodes"] == 1
    block = region(text, OUTPUT_REGION)
    for row in report["per_episode"]:
        result = read_log(row["log"], topics=["/episode/result"]).topic("/episode/result")[-1]
        assert row["landing_error_m"] == pytest.approx(result["landing_error_m"])
        line = re.search(rf"^\s+{row['episode']}\s+.*$", block, re.M)
        assert line is not None, block
        assert f" {result['landing_error_m']:.3f} " in line[0]
        assert line[0].endswith(" success") == bool(result["success"])
    assert f"mean {report['landing_error_m']['mean']:.3f} m" in block
    assert "$ visland demo --episodes 1\n" in block
    assert model_identity(text) == ModelIdentity(
        "models/visland_vision.pt", report["policy_sha256"]
    )
    assert report["policy_sha256"] == sha256_file(SHIPPED_MODEL)
    # The picture the README shows is the run's own plot, linked relative to the README.
    assert (tmp / "docs" / "demo.png").read_bytes() == (demo / "flights.png").read_bytes()
    pic = region(text, PICTURE_REGION)
    assert "](docs/demo.png)" in pic
    error = f"{report['per_episode'][0]['landing_error_m']:.2f} m"
    assert f"landing error {error}" in " ".join(pic.split())


def test_readme_from_a_demo_json_writes_the_same_block(rewritten, tmp_path):
    """``--from-json`` (no flying) renders the same block from the run's ``demo.json``."""
    tmp, demo, before = rewritten
    copy = tmp_path / "README.md"
    copy.write_text(before)
    cfg = ReadmeConfig(
        readme=copy, picture=tmp_path / "docs" / "demo.png", from_json=demo / "demo.json"
    )
    written = run(cfg, io.StringIO())
    report = json.loads((demo / "demo.json").read_text())
    assert written["landing_error_m"] == [r["landing_error_m"] for r in report["per_episode"]]
    ours, theirs = copy.read_text(), (tmp / "README.md").read_text()
    # Log paths are printed relative to the README's folder where they lie below it.
    assert region(ours, OUTPUT_REGION).replace(str(demo), "demo") == region(theirs, OUTPUT_REGION)


def test_readme_refuses_a_report_whose_model_changed(tmp_path):
    """A ``demo.json`` of another version of the checkpoint cannot label this one."""
    ckpt = tmp_path / "model.pt"
    ckpt.write_bytes(b"not the bytes that flew")
    report = {"policy": str(ckpt), "policy_sha256": "0" * 64}
    (tmp_path / "demo.json").write_text(json.dumps(report))
    copy = tmp_path / "README.md"
    copy.write_text(README.read_text())
    cfg = ReadmeConfig(readme=copy, picture=tmp_path / "p.png", from_json=tmp_path / "demo.json")
    with pytest.raises(ReadmeError, match=r"changed since the demo flew it .*fly the demo again"):
        run(cfg, io.StringIO())
    report["policy"], report["policy_sha256"] = "expert", None
    (tmp_path / "demo.json").write_text(json.dumps(report))
    with pytest.raises(ReadmeError, match="not a checkpoint file"):
        run(cfg, io.StringIO())
    assert copy.read_text() == README.read_text()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("no markers at all\n", r"got 0 start and 0 end"),
        (
            "<!-- demo-picture:start -->\n<!-- demo-picture:end -->\n<!-- demo-output:end -->\n"
            "x\n<!-- demo-output:start -->\n",
            r"demo-output end marker comes before its start",
        ),
        (
            "<!-- demo-picture:start -->\n<!-- demo-picture:end -->\n" * 2,
            r"got 2 start and 2 end",
        ),
    ],
)
def test_readme_markers_are_checked_before_anything_flies(tmp_path, text, match):
    """A README without exactly one pair of each marker, in order, stops before the demo flies
    (no output folder is made)."""
    copy = tmp_path / "README.md"
    copy.write_text(text)
    cfg = ReadmeConfig(readme=copy, picture=tmp_path / "p.png", out=tmp_path / "demo")
    with pytest.raises(ReadmeError, match=match):
        run(cfg, io.StringIO())
    assert not (tmp_path / "demo").exists() and copy.read_text() == text


def test_model_identity_needs_the_model_line():
    text = "<!-- demo-output:start -->\n```\n$ visland demo\n```\n<!-- demo-output:end -->\n"
    with pytest.raises(ReadmeError, match="names no model"):
        model_identity(text)
