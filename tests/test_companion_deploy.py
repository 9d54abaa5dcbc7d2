"""The deploy guide as tested commands (docs/deploy.md): the companion's defaults are the
hardware template's, ``visland companion install-service`` sets a board up under a root prefix
(the printed script and the install make the same files; the guide shows that script and every
path it names exists after it), and ``visland companion --check`` prints detections from the
SITL's camera while sending no setpoint.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import subprocess
import sys
from pathlib import Path

from flights import free_ports, sitl_command

from companion.config import CompanionConfig, add_arguments, config_from_args, load_toml
from companion.flight import OffboardConfig
from companion.flightlog import read_log
from companion.install_service import dry_run_script
from companion.packaged import MODEL_FILES, shipped_policy, template
from companion.safety import SafetyConfig
from training.companion_process import sim_companion_args

REPO = Path(__file__).resolve().parent.parent
VISLAND = str(Path(sys.executable).parent / "visland")
DEPLOY = REPO / "docs" / "deploy.md"


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(list(argv))


def test_the_defaults_are_the_hardware_templates_and_the_simulator_passes_its_own():
    from_template = CompanionConfig(**load_toml(template()))
    for f in dataclasses.fields(CompanionConfig):
        if f.name != "policy":
            assert getattr(from_template, f.name) == f.default, f.name
    assert Path(from_template.policy) == shipped_policy()  # relative to the template's folder
    default = config_from_args(_args())  # no --config: the installed template
    assert default == from_template
    assert default.shadow and default.engage_min_range_m == 5.0 and default.thrust_max == 0.9
    assert default.connect.startswith("serial:") and default.camera == "opencv:0"
    # the simulator's launches fly with the flight and safety settings they always had
    sim = config_from_args(_args(*sim_companion_args()))
    assert sim.offboard_config() == OffboardConfig()
    assert sim.safety_config() == SafetyConfig()
    # a calibrated focal length on the command line replaces the template's FOV
    assert config_from_args(_args("--camera-fx-px", "530")).camera_hfov_deg is None


def test_a_relative_policy_in_a_config_is_relative_to_the_file(tmp_path):
    (tmp_path / "conf").mkdir()
    path = tmp_path / "conf" / "c.toml"
    path.write_text('[companion]\npolicy = "m.pt"\nlog_dir = "logs"\n')
    table = load_toml(path)
    assert table["policy"] == str(tmp_path / "conf" / "m.pt")
    assert table["log_dir"] == str(tmp_path / "conf" / "logs")
    path.write_text('[companion]\npolicy = "expert"\n')
    assert load_toml(path)["policy"] == "expert"  # a name, not a path


def _run(*argv: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [VISLAND, *argv], capture_output=True, text=True, timeout=120, cwd=cwd or REPO
    )


def _tree(root: Path) -> dict[str, bytes | None]:
    return {
        str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None)
        for p in sorted(root.rglob("*"))
    }


def test_install_service_makes_what_its_dry_run_prints(tmp_path):
    done, printed = tmp_path / "done", tmp_path / "printed"
    done.mkdir()
    printed.mkdir()
    boot = done / "boot" / "firmware"
    boot.mkdir(parents=True)
    (boot / "cmdline.txt").write_text("console=serial0,115200 console=tty1 root=PARTUUID=1\n")
    (printed / "boot" / "firmware").mkdir(parents=True)
    (printed / "boot" / "firmware" / "cmdline.txt").write_text(
        "console=serial0,115200 console=tty1 root=PARTUUID=1\n"
    )
    res = _run("companion", "install-service", "--root", str(done), "--board", "pi4")
    assert res.returncode == 0, res.stderr
    assert "setup-system.sh: run it on the board as root" in res.stdout
    script = _run("companion", "install-service", "--root", str(printed), "--dry-run")
    assert script.returncode == 0 and not any(printed.glob("etc")), "a dry run writes nothing"
    subprocess.run(["sh", "-c", script.stdout], check=True, timeout=60)
    assert _tree(done) == _tree(printed)
    etc = done / "etc" / "visland"
    cfg = CompanionConfig(**load_toml(etc / "companion.toml"))
    assert cfg.connect == "serial:/dev/ttyAMA0:921600" and cfg.shadow
    assert Path(cfg.policy) == etc / "visland_vision.pt"
    for name in MODEL_FILES:
        assert (etc / name).read_bytes() == (shipped_policy().parent / name).read_bytes()
    assert (boot / "config.txt").read_text().splitlines() == [
        "enable_uart=1",
        "dtoverlay=disable-bt",
    ]
    assert "console=serial0" not in (boot / "cmdline.txt").read_text()
    unit = (done / "etc/systemd/system/visland-companion.service").read_text()
    assert f"ExecStart={Path(sys.prefix) / 'bin' / 'visland'} companion --config" in unit
    assert "User=visland" in unit and "SupplementaryGroups=dialout video" in unit
    setup = (etc / "setup-system.sh").read_text()
    assert "useradd --system --user-group" in setup and "usermod -aG dialout,video" in setup
    assert "chown -R visland:visland /var/lib/visland" in setup
    # the installed config flies the model copied beside it, from any working directory
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    res = _run(
        "companion",
        "--config",
        str(done / "etc/visland/companion.toml"),
        "--camera",
        "udp:127.0.0.1:9",
        "--connect",
        f"udpin:127.0.0.1:{free_ports().remote}",
        "--check",
        "--max-wall-s",
        "0.5",
        cwd=elsewhere,
    )
    assert res.returncode == 1, res.stderr  # no autopilot, no camera: the check fails, cleanly
    assert f"policy {etc / 'visland_vision.pt'}" in res.stdout and "runtime onnx" in res.stderr
    # again: the edited config is kept; the boot lines are not added twice
    (etc / "companion.toml").write_text('[companion]\nconnect = "serial:/dev/ttyUSB0:57600"\n')
    assert _run("companion", "install-service", "--root", str(done)).returncode == 0
    assert "ttyUSB0" in (etc / "companion.toml").read_text()
    assert len((boot / "config.txt").read_text().splitlines()) == 2


def test_install_service_bad_input_names_what_is_wrong(tmp_path):
    res = _run("companion", "install-service", "--root", str(tmp_path / "nope"))
    assert res.returncode == 2 and "--root" in res.stderr and "not a directory" in res.stderr
    res = _run("companion", "install-service", "--root", str(tmp_path), "--venv", "/nope")
    assert res.returncode == 2 and "/nope/bin/visland" in res.stderr
    res = _run("companion", "install-service", "--board", "pi3")
    assert res.returncode == 2 and "invalid choice: 'pi3'" in res.stderr


def test_the_deploy_guide_shows_the_install_and_names_only_paths_it_makes(tmp_path):
    text = DEPLOY.read_text()
    block = re.search(r"<!-- install-service:start.*?-->\n```bash\n(.*?)```", text, re.S)
    assert block, "docs/deploy.md: no install-service block"
    assert block.group(1) == dry_run_script(Path("/"), "pi4", Path("/opt/visland"))
    assert _run("companion", "install-service", "--root", str(tmp_path)).returncode == 0
    named = set(re.findall(r"(/(?:etc/visland|var/lib/visland|etc/systemd)[\w./-]*)", text))
    named |= set(re.findall(r"(/boot/firmware/[\w.]+)", text))
    assert "/etc/visland/companion.toml" in named and "/var/lib/visland/flights" in named
    for path in sorted(named):
        path = path.rstrip(".")
        if "*" in path or path.endswith("cmdline.txt"):  # flight logs; only edited if there
            continue
        assert (tmp_path / path.lstrip("/")).exists(), f"docs/deploy.md names {path}"


def test_check_prints_detections_from_the_sitl_and_sends_no_setpoint(procs, tmp_path):
    ports = free_ports()
    sitl_dir = tmp_path / "sitl"
    sitl = procs.start(
        "sitl",
        sitl_command(
            ports,
            sitl_dir,
            "--render",
            "--no-groundtruth",
            "--no-lockstep",
            "--episodes",
            "1",
            "--hold-timeout-s",
            "6",
            max_wall_s=40,
        ),
    )
    check = subprocess.run(
        [
            VISLAND,
            "companion",
            "--check",
            "--connect",
            f"udpin:127.0.0.1:{ports.remote}",
            "--camera",
            f"udp:127.0.0.1:{ports.camera}",
            "--max-wall-s",
            "4",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert check.returncode == 0, check.stdout + check.stderr
    out = check.stdout
    assert "link discovered" in out and "param MPC_THR_HOVER = " in out
    assert re.search(r"camera \d+\.\d fps  pad seen \(p = [\d.]+\), bearing [-+]", out), out
    assert "check passed" in out and "setpoints sent 0" in out
    assert sitl.wait(60) == 0, procs.text("sitl")
    flight = read_log(sitl_dir / "sitl_seed0_ep0000.mcap")
    received = {t for t in flight.messages if t.startswith("/mavlink/in/")}
    assert "/mavlink/in/HEARTBEAT" in received  # connected...
    assert "/mavlink/in/SET_ATTITUDE_TARGET" not in received  # ...and no setpoint
    assert not any("command 176" in e["text"] for e in flight.topic("/events"))  # no mode
