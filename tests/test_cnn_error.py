"""``visland pad error``: the CNN's error per scenario and altitude band, in the pad's axes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sitl_sim.scenario import load_scenario
from tools.cli import main
from tools.cnn_error import parse_band
from training.perception_data import chunk_pad_frame


def test_pad_error_end_to_end(capsys):
    scenarios = "--scenario configs/scenario.toml --scenario configs/sites/rover_slow.toml"
    code = main(
        ["pad", "error", *scenarios.split(), *"--band 20-40 --frames 64 --chunk 16 --json".split()]
    )
    out = capsys.readouterr()
    assert code == 0, out.err
    res = json.loads(out.out)
    assert res["seed"] == 500 and res["thresholds"]["seen"] == 0.9
    nominal, rover = res["scenarios"]
    assert rover["scenario"].endswith("rover_slow.toml")
    for sc in (nominal, rover):
        (band,) = sc["bands"]
        assert band["band_m"] == [20.0, 40.0] and band["frames"] == 64
        assert band["in_view"] >= 60  # level frames with the pad in view (a few near the edge)
        assert 0.0 <= band["seen"] <= band["acquired"] <= 1.0
        assert band["error_m_median"] <= band["error_m_p90"]
        # the median of a component never exceeds the median of the whole error by much
        assert abs(band["right_m_median"]) <= band["error_m_p90"]
    # the shipped CNN on the paper's pad, still, at 20-40 m: seen, and placed within 0.4 m
    (band,) = nominal["bands"]
    assert band["seen"] > 0.8 and band["error_m_median"] < 0.4 and band["error_px_median"] < 2.5
    # ... and finds no pad in the bare ground 40-300 m from it (the rover's: its own ground)
    assert band["false_seen"] <= band["false_acquired"] <= 0.1
    assert 0.0 <= rover["bands"][0]["false_seen"] <= 1.0
    # the same figures come back on a rerun (rendering and the CNN are seeded)
    assert (
        main(["pad", "error", "--band", "20-40", "--frames", "64", "--chunk", "16", "--json"]) == 0
    )
    assert json.loads(capsys.readouterr().out)["scenarios"][0] == nominal


def test_pad_error_refuses_a_bad_band_or_scenario(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["pad", "error", "--band", "40"])
    assert exc.value.code == 2 and "expected LO-HI" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    rover = open("configs/sites/rover_slow.toml").read()
    assert 'motion = "rover"' in rover
    bad.write_text(rover.replace('motion = "rover"', 'motion = "hovercraft"'))
    assert main(["pad", "error", "--scenario", str(bad), "--frames", "8", "--json"]) != 0
    err = capsys.readouterr().err
    assert "bad.toml" in err and "motion" in err
    for text in ("8-8", "-1-3", "a-b", "3-"):
        with pytest.raises(ValueError):
            parse_band(text)


def test_chunk_pad_frame_is_the_carriers_axes():
    """A still pad: north-east-down; a rover: a rotation about the vertical by its heading,
    drawn per chunk as an episode's site is."""
    nominal = load_scenario("configs/scenario.toml")
    assert np.array_equal(
        chunk_pad_frame(500, 0, nominal.visual, nominal.pad, nominal.terrain), np.eye(3)
    )
    rover = load_scenario("configs/sites/rover_slow.toml")
    frames = [chunk_pad_frame(500, k, rover.visual, rover.pad, rover.terrain) for k in range(4)]
    for r in frames:
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and abs(r[2, 2] - 1.0) < 0.05
    headings = {round(float(np.degrees(np.arctan2(r[1, 0], r[0, 0]))), 3) for r in frames}
    assert len(headings) == 4  # each chunk its own rover
    assert np.array_equal(
        frames[1], chunk_pad_frame(500, 1, rover.visual, rover.pad, rover.terrain)
    )


def test_site_weights_give_the_sites_their_share_of_the_cnns_frames():
    from training.perception_data import has_site, site_weights
    from training.profiles import PROFILES, PipelineError, Profile
    from training.worlds import load_worlds

    worlds = load_worlds("configs/train/robust_sites.toml").worlds
    shares = tuple(w.share for w in worlds)
    sites = tuple(has_site(w.scenario.pad, w.scenario.terrain) for w in worlds)
    named = {w.name for w, s in zip(worlds, sites, strict=True) if s}
    assert named == {"rover_mixed", "deck_mixed", "ground_mixed", "mars_ground"}
    assert site_weights(shares, sites, None) == shares
    w = np.array(site_weights(shares, sites, 0.55))
    assert w[list(sites)].sum() == pytest.approx(0.55 * sum(shares))
    # within a group, the worlds keep their proportions
    rover, deck = (
        (names := [x.name for x in worlds]).index("rover_mixed"),
        names.index("deck_mixed"),
    )
    assert w[rover] / w[deck] == pytest.approx(shares[rover] / shares[deck])
    assert site_weights((1.0, 2.0), (False, False), 0.5) == (1.0, 2.0)
    assert PROFILES["robust_sites_cnn"].perception_site_share == 0.55
    with pytest.raises(PipelineError, match=r"perception_site_share = 1\.0"):
        Profile(**{**PROFILES["quick"].to_dict(), "perception_site_share": 1.0})
