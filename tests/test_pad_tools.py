"""``visland pad info|print|check``: each command run end to end (the CLI's ``main`` with argv, or
``visland`` as its own process), its outcome asserted — the envelope's pixel widths, the contrast
warnings, the PDF's pages and scale read back from the file's bytes (tests/pdf_reader.py), the
shipped model's detection on frames the simulator renders — and each bad input's exit code."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO, visland
from pdf_reader import PdfFile
from PIL import Image

from sitl_sim.render.terrain import FAMILIES
from tools.cli import main
from tools.pad_info import ACQUIRE_PX, acquire_altitude_m, pad_width_px, start_altitudes_m
from tools.pad_print import MARGIN_PT, OVERLAP_PT, PAPERS, layout

PT_PER_CM = 72.0 / 2.54
SCALE_BAR_PT = 283.465  # 10 cm


def run(capsys, *argv: str) -> tuple[int, str, str]:
    """``visland ARGV`` in this process: (exit code, stdout, stderr)."""
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def info_json(capsys, *argv: str) -> dict:
    code, out, err = run(capsys, "pad", "info", *argv, "--json")
    assert code == 0, err
    return json.loads(out)


# --------------------------------------------------------------------------- pad info


def test_pixel_width_of_a_known_pad_at_a_known_altitude(capsys):
    expected = 128 * 4.0 / (2 * 100.0 * math.tan(math.radians(22.5)))  # 6.18 px
    assert pad_width_px(4.0, 100.0, 45.0, 128) == pytest.approx(expected, rel=1e-12)
    info = info_json(capsys, "--pad", "paper", "--no-families")
    assert info["size_m"] == [4.0, 4.0]
    at_100 = [r for r in info["curve"] if r["altitude_m"] == 100.0]
    assert at_100 and at_100[0]["width_px"] == pytest.approx(expected, rel=1e-9)
    # the threshold is the paper pad's width at the scenario's highest start altitude ...
    assert info["acquire_px"] == pytest.approx(expected, rel=1e-12)
    assert info["acquire_altitude_m"] == pytest.approx(100.0)
    assert info["start_altitude_m"] == pytest.approx([75.0, 100.0])
    # ... on another camera the threshold stays in the model's pixels: half the resolution,
    # half the altitude
    half = info_json(capsys, "--pad", "paper", "--no-families", "--resolution", "64")
    assert half["acquire_altitude_m"] == pytest.approx(50.0)
    assert half["acquire_px"] == pytest.approx(expected)


def test_the_threshold_is_the_scenarios_start_altitudes():
    """The definition holds against the scenario file itself: the 4 m paper pad is acquired
    from exactly the scenario's start altitude range."""
    scenario = tomllib.loads((REPO / "configs" / "scenario.toml").read_text())
    lo, hi = scenario["initial_state"]["altitude_m"]
    assert start_altitudes_m(4.0) == pytest.approx((lo, hi))
    assert pad_width_px(4.0, hi) == pytest.approx(ACQUIRE_PX)


def test_a_1m_helipad_is_acquired_from_25m(capsys):
    info = info_json(capsys, "--pad", "helipad_1m", "--no-families")
    assert info["acquire_altitude_m"] == pytest.approx(25.0)
    assert info["start_altitude_m"] == pytest.approx([18.75, 25.0])
    assert acquire_altitude_m(2.0) == pytest.approx(50.0)
    widths = {r["altitude_m"]: r["width_px"] for r in info["curve"]}
    assert widths[10.0] == pytest.approx(128 / (20 * math.tan(math.radians(22.5))))
    code, out, _ = run(capsys, "pad", "info", "--pad", "helipad_1m", "--no-families")
    assert code == 0
    assert "highest altitude to acquire it: 25.0 m" in out
    assert "altitude_m = [18.8, 25.0]" in out
    assert "6.18 px" in out and "75-100 m" in out


def test_contrast_warning_on_a_ground_as_bright_as_the_green_square(capsys, tmp_path):
    # grey 153 has luma 153, the paper pad's green square's (BT.601: (77+150+29) x 153 / 256)
    ground = tmp_path / "my_field.png"
    Image.fromarray(np.full((60, 80, 3), 153, np.uint8)).save(ground)
    info = info_json(capsys, "--pad", "paper", "--ground", str(ground), "--no-families")
    (row,) = info["contrast"]
    assert row["ground"] == "my_field.png"
    assert row["contrast"]["square"] == pytest.approx(0.0, abs=1.0)
    assert row["vanishes"] == ["square"]  # the red cross still contrasts
    assert any("square vanishes" in w and "cross is left" in w for w in info["warnings"])
    code, out, _ = run(
        capsys, "pad", "info", "--pad", "paper", "--ground", str(ground), "--no-families"
    )
    assert code == 0
    assert "warning: on my_field.png: the pad's square vanishes" in out
    # the quadrant target keeps both parts on that ground: no warning
    quad = info_json(capsys, "--pad", "quadrant_2m", "--ground", str(ground), "--no-families")
    assert quad["warnings"] == []


def test_contrast_against_the_simulators_grounds(capsys):
    """On sand the paper pad's green square has the sand's luma: only the cross is left."""
    info = info_json(capsys, "--pad", "paper")
    rows = {r["ground"]: r for r in info["contrast"]}
    assert set(rows) == {"nominal", *FAMILIES}  # every ground the simulator draws
    assert rows["sand"]["vanishes"] == ["square"]
    assert "square" not in rows["nominal"]["vanishes"]
    helipad = info_json(capsys, "--pad", "helipad_1m")
    assert all("ring" not in r["vanishes"] for r in helipad["contrast"])


def test_pad_info_plot(capsys, tmp_path):
    out = tmp_path / "curve.png"
    code, text, err = run(capsys, "pad", "info", "--pad", "helipad_1m", "--plot", str(out))
    assert code == 0, err
    assert f"wrote {out}" in text
    with Image.open(out) as img:
        assert img.format == "PNG" and img.size[0] > 1000  # two panels: curve and contrast


# --------------------------------------------------------------------------- pad print


def _expected_tiles(side_m: float, page: tuple[float, float]) -> int:
    """Tiles of a square pad on pages of ``page`` points: 12 mm margins, 10 mm shared strips."""
    pad = side_m * 100 * PT_PER_CM
    n = []
    for length in page:
        content = length - 2 * 1.2 * PT_PER_CM
        n.append(1 if pad <= content else 1 + math.ceil((pad - content) / (content - PT_PER_CM)))
    return n[0] * n[1]


def _check_scale_bars(pdf: PdfFile) -> None:
    for page in pdf.pages:
        (bar,) = page.scale_bars
        x0, y0, x1, y1 = bar
        assert y0 == pytest.approx(y1)
        assert abs(x1 - x0) == pytest.approx(SCALE_BAR_PT, abs=0.5)


def test_print_helipad_on_a4_pages_at_true_scale(tmp_path):
    out = tmp_path / "helipad.pdf"
    proc = visland("pad", "print", "--pad", "helipad_1m", "--out", str(out), "--paper", "a4")
    assert proc.returncode == 0, proc.stderr
    # a 1 m pad on A4 (186 x 274 mm inside the margins): 6 columns x 4 rows, + the map
    assert _expected_tiles(1.0, (595.28, 841.89)) == 24
    assert "on 25 pages of A4 portrait" in proc.stdout
    pdf = PdfFile(out)
    assert len(pdf.pages) == 25
    assert all(p.media_box == (0.0, 0.0, 595.28, 841.89) for p in pdf.pages)
    _check_scale_bars(pdf)
    title = " ".join(pdf.pages[0].texts)
    assert "helipad_1m: 1 m x 1 m at true scale" in title and "25 pages" in title
    # the tiles' images, put back at their place on the pad, span exactly 1 m: true scale
    lay = layout((1.0, 1.0), "a4")
    step_x, step_y = lay.step_pt
    left, right, top, bottom = [], [], [], []
    for k, page in enumerate(pdf.pages[1:]):
        r, c = divmod(k, lay.cols)
        (img,) = page.images
        x, y, w, h = img["rect_pt"]
        pad_x = x - MARGIN_PT + c * step_x
        pad_top = (595.28 if lay.landscape else 841.89) - MARGIN_PT - (y + h) + r * step_y
        left.append(pad_x)
        right.append(pad_x + w)
        top.append(pad_top)
        bottom.append(pad_top + h)
        assert w / img["width_px"] == pytest.approx(h / img["height_px"])  # square pixels
    metre_pt = 100 * PT_PER_CM
    assert min(left) == pytest.approx(0.0, abs=0.5)
    assert max(right) == pytest.approx(metre_pt, abs=0.5)
    assert min(top) == pytest.approx(0.0, abs=0.5)
    assert max(bottom) == pytest.approx(metre_pt, abs=0.5)


def test_print_paper_pad_on_a3(capsys, tmp_path):
    out = tmp_path / "paper.pdf"
    code, text, err = run(capsys, "pad", "print", "--out", str(out), "--paper", "a3")
    assert code == 0, err
    pages = 1 + _expected_tiles(4.0, (841.89, 1190.55))
    assert f"on {pages} pages of A3" in text
    pdf = PdfFile(out)
    assert len(pdf.pages) == pages
    assert {p.media_box for p in pdf.pages} == {(0.0, 0.0, 841.89, 1190.55)}
    _check_scale_bars(pdf)
    # the tile at the pad's centre shows the red cross, a corner tile the green square
    lay = layout((4.0, 4.0), "a3")
    centre = pdf.pages[1 + (lay.rows // 2) * lay.cols + lay.cols // 2].images[0]["rgb"]
    corner = pdf.pages[1].images[0]["rgb"]
    assert tuple(centre[centre.shape[0] // 2, centre.shape[1] // 2]) == (204, 20, 20)
    assert tuple(corner[0, 0]) == (63, 216, 63)


@pytest.mark.parametrize("paper", sorted(PAPERS))
def test_print_page_sizes(capsys, tmp_path, paper):
    out = tmp_path / f"quad_{paper}.pdf"
    code, _, err = run(
        capsys, "pad", "print", "--pad", "quadrant_2m", "--out", str(out), "--paper", paper
    )
    assert code == 0, err
    pdf = PdfFile(out)
    size = {"a4": (595.28, 841.89), "a3": (841.89, 1190.55), "letter": (612, 792),
            "poster": (2383.94, 3370.39)}[paper]  # fmt: skip
    lay = layout((2.0, 2.0), paper)
    want = (0.0, 0.0, *(size[::-1] if lay.landscape else size))
    assert all(p.media_box == pytest.approx(want) for p in pdf.pages)
    assert len(pdf.pages) == 1 + min(_expected_tiles(2.0, size), _expected_tiles(2.0, size[::-1]))
    _check_scale_bars(pdf)


def test_print_png_for_a_print_shop(capsys, tmp_path):
    out = tmp_path / "helipad.png"
    code, text, err = run(
        capsys, "pad", "print", "--pad", "helipad_1m", "--png", "--dpi", "40", "--out", str(out)
    )
    assert code == 0, err
    assert "40 dpi" in text
    with Image.open(out) as img:
        assert img.size == (round(40 / 0.0254), round(40 / 0.0254))  # 1 m at 40 dpi: 1575 px
        assert img.info["dpi"] == pytest.approx((40, 40), abs=0.01)
    code, _, err = run(capsys, "pad", "print", "--png", "--dpi", "300", "--out", str(out))
    assert code == 2 and "use --dpi 76 or less" in err


def test_tile_layout_overlaps():
    lay = layout((4.0, 4.0), "a4")
    cw, ch = lay.content_pt
    assert cw - lay.step_pt[0] == pytest.approx(OVERLAP_PT)
    # the tiles cover the pad, and no fewer would
    assert (lay.cols - 1) * lay.step_pt[0] + cw >= lay.pad_pt[0]
    assert (lay.cols - 2) * lay.step_pt[0] + cw < lay.pad_pt[0]
    assert (lay.rows - 1) * lay.step_pt[1] + ch >= lay.pad_pt[1]


# --------------------------------------------------------------------------- pad check


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> dict[str, Path]:
    """Frames the simulator's camera renders (its configured renderer, the nominal ground and
    the paper pad), straight down from 20 m: over the pad, 3 m north and 2 m east of it, and
    over bare ground; and a 640 x 480 photo of 60 deg vertical field of view over the pad."""
    from dataclasses import replace

    from sitl_sim.config import load_sim
    from sitl_sim.render.scene import make_renderer

    cam = load_sim().camera
    big = replace(cam, width_px=640, height_px=480, fov_deg=60.0)
    d = tmp_path_factory.mktemp("frames")
    shots = {
        "pad": ((0.0, 0.0, -20.0), cam),
        "offset": ((3.0, 2.0, -20.0), cam),
        "bare": ((150.0, 120.0, -20.0), cam),
        "photo": ((3.0, 2.0, -20.0), big),
    }
    out = {}
    renderer = make_renderer(cam.renderer)
    try:
        for name, (pos, cfg) in shots.items():
            out[name] = d / f"{name}.png"
            Image.fromarray(renderer.render(pos, (1.0, 0.0, 0.0, 0.0), cfg)).save(out[name])
    finally:
        renderer.close()
    return out


def test_check_detects_the_pad_from_20m(capsys, frames):
    code, out, err = run(capsys, "pad", "check", str(frames["pad"]))
    assert code == 0, err
    assert "pad DETECTED" in out
    res = json.loads(run(capsys, "pad", "check", str(frames["offset"]), "--json")[1])
    assert res["detected"] and res["visibility"] >= res["threshold"]
    # the camera 3 m north and 2 m east of the pad: the pad lies back and left
    assert res["bearing_forward_deg"] == pytest.approx(-math.degrees(math.atan(3 / 20)), abs=1.5)
    assert res["bearing_right_deg"] == pytest.approx(-math.degrees(math.atan(2 / 20)), abs=1.5)


def test_check_crops_a_wide_photo_to_the_models_view(capsys, frames):
    f = 240 / math.tan(math.radians(30))  # 480 px over 60 deg vertical
    hfov = 2 * math.degrees(math.atan(320 / f))
    code, out, err = run(
        capsys, "pad", "check", str(frames["photo"]), "--photo-hfov-deg", f"{hfov}", "--json"
    )
    assert code == 0, err
    res = json.loads(out)
    assert res["bearing_forward_deg"] == pytest.approx(-math.degrees(math.atan(3 / 20)), abs=1.5)
    assert res["bearing_right_deg"] == pytest.approx(-math.degrees(math.atan(2 / 20)), abs=1.5)


def test_check_bare_ground_is_not_detected(capsys, frames):
    code, out, _ = run(capsys, "pad", "check", str(frames["bare"]))
    assert code == 1
    assert "pad NOT DETECTED" in out


# --------------------------------------------------------------------------- bad input


@pytest.fixture
def bad_files(tmp_path) -> dict[str, Path]:
    typo = tmp_path / "typo.toml"
    typo.write_text('name = "x"\nsize_m = [1.0, 1.0]\npattern = "helipad"\ncolour = "red"\n')
    garbage = tmp_path / "garbage.png"
    garbage.write_text("not an image")
    return {"typo": typo, "garbage": garbage, "missing": tmp_path / "nowhere.toml"}


@pytest.mark.parametrize(
    "argv, names",
    [
        (["info", "--pad", "{missing}"], ["nowhere.toml", "not found"]),
        (["info", "--pad", "{typo}"], ["typo.toml", "'colour'"]),
        (["info", "--pad", "paper", "--ground", "{garbage}"], ["garbage.png", "--ground"]),
        (["info", "--pad", "paper", "--ground", "{missing}"], ["nowhere.toml", "--ground"]),
        (["print", "--pad", "{missing}", "--out", "{tmp}/x.pdf"], ["nowhere.toml"]),
        (["print", "--pad", "{typo}", "--out", "{tmp}/x.pdf"], ["typo.toml", "'colour'"]),
        (["check", "{missing}"], ["nowhere.toml"]),
        (["check", "{garbage}"], ["garbage.png", "readable"]),
        (["check", "{garbage}", "--checkpoint", "{missing}"], ["garbage.png"]),
    ],
)
def test_bad_input_exits_2_naming_the_file(capsys, tmp_path, bad_files, argv, names):
    fill = {**{k: str(v) for k, v in bad_files.items()}, "tmp": str(tmp_path)}
    code, _, err = run(capsys, "pad", *(a.format(**fill) for a in argv))
    assert code == 2
    assert err.startswith("visland pad: error:") and err.count("\n") == 1
    for name in names:
        assert name in err


def test_check_with_a_missing_checkpoint_exits_2(capsys, frames, tmp_path):
    code, _, err = run(
        capsys, "pad", "check", str(frames["pad"]), "--checkpoint", str(tmp_path / "no.pt")
    )
    assert code == 2 and "no.pt" in err
