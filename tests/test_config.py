"""Configuration and scenario files: typed errors naming the file and field."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from helpers import config_plus, edited_config
from scipy.stats import qmc

from sitl_sim.config import CONFIG_DIR, load_sim, load_vehicle, planet
from sitl_sim.errors import ConfigError
from sitl_sim.scenario import InitialStateSampler, load_scenario


def test_default_configs_match_table_1():
    v = load_vehicle()
    assert v.mass_kg == 1.0 and v.arm_length_m == 0.125
    assert v.inertia_diag_kg_m2 == (0.009, 0.009, 0.016)
    assert v.max_total_thrust_n(planet("earth")) == 25.0
    assert v.max_total_thrust_n(planet("mars")) == 25.0  # the stated design assumption
    s = load_sim()
    assert s.physics_rate_hz % s.control_rate_hz == 0 and s.physics_rate_hz >= 250
    assert (s.camera.width_px, s.camera.height_px, s.camera.fov_deg) == (128, 128, 45.0)
    assert s.control_rate_hz == 10 and s.radar.max_range_m == 150.0


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            "mass_kg = 1.0 ",
            "mass_kg = -1.0 ",
            r"vehicle.toml: \[vehicle\] mass_kg = -1.0; expected a number > 0 and <= 100 \(kg\)",
        ),
        (
            "mass_kg = 1.0 ",
            'mass_kg = "heavy" ',
            r"\[vehicle\] mass_kg = 'heavy'; expected a number",
        ),
        (
            "inertia_diag_kg_m2 = [0.009, 0.009, 0.016]",
            "inertia_diag_kg_m2 = [0.009, 0.009]",
            r"\[vehicle\] inertia_diag_kg_m2 = \[0.009, 0.009\]; expected a list of 3 numbers",
        ),
        (
            "inertia_diag_kg_m2 = [0.009, 0.009, 0.016]",
            "inertia_diag_kg_m2 = [0.009, 0.0, 0.016]",
            r"inertia_diag_kg_m2 = \[0.009, 0.0, 0.016\]; expected 3 numbers, each in "
            r"\[1e-06, 100\] \(kg m\^2\)",
        ),
        (
            "max_rate_rad_s = [3.5, 3.5, 1.5]",
            "max_rate_rad_s = [3.5, nan, 1.5]",
            r"\[rate_controller\] max_rate_rad_s = \[3.5, nan, 1.5\]; expected 3 numbers",
        ),
        ("mass_kg = 1.0 ", "mass_kgg = 1.0 ", r"unknown key\(s\) \['mass_kgg'\]"),
        ("[rate_controller]", "[rate_control]", r"unknown section\(s\) \['\[rate_control\]'\]"),
        ("[vehicle]", "[vehicles]", r"unknown section\(s\) \['\[vehicles\]'\]"),
        ("earth = 25.0 ", "venus = 25.0 ", r"\[vehicle.max_total_thrust_n\] unknown key"),
        ("earth = 25.0 ", "earth = 0.0 ", r"\[vehicle.max_total_thrust_n\] earth = 0.0; expected"),
        # the old single figure: thrust would silently be the same in any air
        (
            "[vehicle.max_total_thrust_n]",
            "max_total_thrust_n = 25.0\n[vehicle.thrust_notes]",
            r"\[vehicle\] max_total_thrust_n = 25\.0; expected a table "
            r"\[vehicle\.max_total_thrust_n\] with T_max \(N\) per planet",
        ),
        (
            "mars = 25.0",
            "venus = 25.0",
            r"\[vehicle\.max_total_thrust_n\] unknown key\(s\) \['venus'\]; expected "
            r"\['earth', 'mars'\]",
        ),
        (
            "mars = 25.0",
            "mars = 0.0",
            r"vehicle\.toml: \[vehicle\.max_total_thrust_n\] mars = 0\.0; expected a number > 0",
        ),
        (
            "[vehicle.max_total_thrust_n]\n",
            "[thrust_by_planet]\n",
            r"unknown section\(s\) \['\[thrust_by_planet\]'\]",
        ),
    ],
)
def test_bad_vehicle_values_name_file_and_field(tmp_path, old, new, match):
    with pytest.raises(ConfigError, match=match) as info:
        load_vehicle(edited_config(tmp_path, "vehicle.toml", old, new))
    assert str(tmp_path / "vehicle.toml") in str(info.value)


def test_a_vehicle_needs_its_own_mass_and_thrust(tmp_path):
    """A vehicle's physics has no nominal value: a missing mass or T_max is refused, never
    silently a 1 kg quad; the rate controller's gains default to the shipped tuning."""
    path = edited_config(tmp_path, "vehicle.toml", "mass_kg = 1.0 ", "# no mass ")
    with pytest.raises(ConfigError, match=r"\[vehicle\] missing key 'mass_kg'; expected a number"):
        load_vehicle(path)
    text = (CONFIG_DIR / "vehicle.toml").read_text()
    path.write_text(text[: text.index("\n[vehicle.max_total_thrust_n]")])
    with pytest.raises(
        ConfigError, match=r"missing table \[vehicle.max_total_thrust_n\] \(T_max in N per planet"
    ):
        load_vehicle(path)
    path.write_text(text[: text.index("\n[rate_controller]")])
    assert load_vehicle(path) == load_vehicle()


def test_keys_left_out_take_their_nominal_values(tmp_path):
    """A sim file that says only what differs (one sensor's noise): every other key is the
    shipped configs/sim.toml's, which states exactly the declared defaults."""
    path = tmp_path / "sim.toml"
    path.write_text('[imu]\ngyro_noise_std_rad_s = 0.01\n[camera]\nrenderer = "fast"\n')
    got = load_sim(path)
    assert got.imu.gyro_noise_std_rad_s == 0.01
    assert replace(got, imu=replace(got.imu, gyro_noise_std_rad_s=0.003)) == load_sim()
    path.write_text("")
    assert load_sim(path) == replace(
        load_sim(), camera=replace(load_sim().camera, renderer="pybullet")
    )
    path.write_text("[imu]\ngyro_noise = 0.01\n")
    with pytest.raises(ConfigError, match=r"sim.toml: \[imu\] unknown key\(s\) \['gyro_noise'\]"):
        load_sim(path)


def test_unknown_key_is_reported(tmp_path):
    path = edited_config(tmp_path, "vehicle.toml", "mass_kg = 1.0 ", "mass_kg = 1.0\nmas_kg = 2.0 ")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['mas_kg'\]"):
        load_vehicle(path)


def test_unknown_scenario_section_or_world_key_is_refused(tmp_path):
    """A misspelt section used to be ignored silently: the flight went on in the nominal world."""
    path = config_plus(tmp_path, "\n[wnd]\nspeed_m_s = [0, 5]\n")
    with pytest.raises(
        ConfigError, match=r"scenario\.toml: unknown section\(s\) \['\[wnd\]'\]; expected"
    ):
        load_scenario(path)
    path = edited_config(
        tmp_path, "scenario.toml", 'planet = "earth"', 'planet = "earth"\nplanett = "x"'
    )
    with pytest.raises(ConfigError, match=r"\[world\] unknown key\(s\) \['planett'\]"):
        load_scenario(path)


def test_rates_must_be_integer_multiples(tmp_path):
    path = edited_config(tmp_path, "sim.toml", "physics_rate_hz = 250", "physics_rate_hz = 255")
    with pytest.raises(
        ConfigError, match=r"sim\.toml: \[sim\] physics_rate_hz = 255 .*integer multiple"
    ):
        load_sim(path)


def test_unknown_planet(tmp_path):
    with pytest.raises(ConfigError, match=r"planet = 'venus'; expected one of \['earth', 'mars'\]"):
        load_sim(edited_config(tmp_path, "sim.toml", 'planet = "earth"', 'planet = "venus"'))
    with pytest.raises(ConfigError, match="unknown planet 'pluto'"):
        planet("pluto")
    with pytest.raises(ConfigError, match=r"\[world\] planet = 'venus'"):
        load_scenario(
            edited_config(tmp_path, "scenario.toml", 'planet = "earth"', 'planet = "venus"')
        )


def test_malformed_toml_names_the_file(tmp_path):
    bad = tmp_path / "scenario.toml"
    bad.write_text("[initial_state\nroll_pitch_deg = [")
    with pytest.raises(ConfigError, match=r"scenario.toml: not valid TOML"):
        load_scenario(bad)
    with pytest.raises(ConfigError, match="file not found"):
        load_scenario(tmp_path / "nope.toml")


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        ("altitude_m = [75.0, 100.0]", "altitude_m = [100.0, 75.0]", "lo <= hi"),
        ("altitude_m = [75.0, 100.0]", "altitude_m = [-5.0, 100.0]", "expected > 0"),
        ("altitude_m = [75.0, 100.0]", 'altitude_m = "high"', r"expected \[lo, hi\]"),
        ('sampler = "sobol+uniform"', 'sampler = "halton"', "sampler = 'halton'"),
        ("yaw_deg = [-180.0, 180.0]\n", "", "missing key 'yaw_deg'"),
        (  # physical bounds: a start the radar cannot see nor the episode reach down from
            "altitude_m = [75.0, 100.0]",
            "altitude_m = [2000.0, 2000.0]",
            r"scenario\.toml: \[initial_state\] altitude_m = \[2000\.0, 2000\.0\]; expected "
            r"finite \[lo, hi\] with 0 < lo <= hi <= 300 \(m\)",
        ),
        (
            "roll_pitch_deg = [-1.5, 1.5]",
            "roll_pitch_deg = [-120.0, 1.5]",
            r"\[initial_state\] roll_pitch_deg = \[-120\.0, 1\.5\]; expected .*-90 <= lo",
        ),
    ],
)
def test_bad_scenarios(tmp_path, old, new, match):
    with pytest.raises(ConfigError, match=match):
        load_scenario(edited_config(tmp_path, "scenario.toml", old, new))


def test_a_scalar_is_a_fixed_span(tmp_path):
    """``key = x`` means ``[x, x]`` for every span key (a fixed value every episode)."""
    path = edited_config(tmp_path, "scenario.toml", "altitude_m = [75.0, 100.0]", "altitude_m = 80")
    path.write_text(path.read_text() + "\n[wind]\nspeed_m_s = 5.0\ndirection_deg = 90\n")
    sc = load_scenario(path)
    assert sc.altitude_m == (80.0, 80.0) and sc.wind.speed_m_s == (5.0, 5.0)
    assert sc.wind.direction_deg == (90.0, 90.0)
    assert -InitialStateSampler(sc, 3).sample(0).pos_ned_m[2] == 80.0
    path.write_text(path.read_text().replace("speed_m_s = 5.0", "speed_m_s = 200.0"))
    with pytest.raises(ConfigError, match=r"\[wind\] speed_m_s = \[200\.0, 200\.0\]"):
        load_scenario(path)


def test_sampler_is_deterministic_and_within_ranges():
    sc = load_scenario()
    a = [InitialStateSampler(sc, 11).sample(i) for i in range(64)]
    b = InitialStateSampler(sc, 11)
    assert [b.sample(i) for i in reversed(range(64))][::-1] == a  # order of asking is irrelevant
    assert InitialStateSampler(sc, 12).sample(0) != a[0]
    for st in a:
        assert -5 <= st.pos_ned_m[0] <= 5 and -5 <= st.pos_ned_m[1] <= 5
        assert 75 <= -st.pos_ned_m[2] <= 100
        assert 0.0 <= st.vel_ned_m_s[2] <= 0.5
        assert all(abs(np.degrees(e)) <= 1.5 for e in st.euler_rad[:2])
        assert st.rate_frd_rad_s == (0.0, 0.0, 0.0)


def test_sobol_covers_the_space_more_evenly_than_uniform():
    sc = load_scenario()
    from dataclasses import replace

    uni = replace(sc, sampler="uniform")

    def unit(scn) -> np.ndarray:
        pts = []
        for i in range(256):
            st = InitialStateSampler(scn, 3).sample(i)
            pts.append(
                [
                    (st.pos_ned_m[0] + 5) / 10,
                    (st.pos_ned_m[1] + 5) / 10,
                    (-st.pos_ned_m[2] - 75) / 25,
                    (st.vel_ned_m_s[0] + 1) / 2,
                    (st.vel_ned_m_s[1] + 1) / 2,
                    st.vel_ned_m_s[2] / 0.5,
                ]
            )
        return np.asarray(pts)

    assert qmc.discrepancy(unit(sc)) < 0.5 * qmc.discrepancy(unit(uni))


def test_cli_reports_a_bad_scenario_in_one_line(tmp_path):
    bad = edited_config(tmp_path, "scenario.toml", 'planet = "earth"', 'planet = "venus"')
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "demo", "--scenario", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "visland demo: error:" in proc.stderr and "venus" in proc.stderr
