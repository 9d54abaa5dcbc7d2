"""``visland companion install-service``: set a board up to run the companion as a service.

What it does, in this order, under a root prefix (``--root``, default ``/``; a test or an SD
card image mounted elsewhere uses another):

1. ``/etc/visland/``: the hardware config template (``companion.toml``, its ``connect`` set to
   the board's serial port) and the shipped model beside it (the checkpoint and its two ONNX
   graphs; the template's ``policy = "visland_vision.pt"`` is relative to the config's folder).
   An existing ``companion.toml`` is kept (``--force`` replaces it).
2. ``/var/lib/visland/flights/``: the flight logs.
3. ``/etc/systemd/system/visland-companion.service``: ``User=visland``, groups ``dialout``
   (the serial port) and ``video`` (the camera), ``ExecStart`` this install's ``visland``.
4. Raspberry Pi: the UART on GPIO14/15 in ``/boot/firmware/config.txt`` (Pi 4:
   ``dtoverlay=disable-bt``, else ``/dev/ttyAMA0`` is the Bluetooth UART and the companion
   waits for an autopilot for ever; Pi 5: ``dtparam=uart0``), and no login console on it
   (``cmdline.txt``).
5. The system part, which only root on the board itself can do: the ``visland`` user and its
   groups, the owner of ``/var/lib/visland``, systemd. Run as root with ``--root /`` it is run;
   otherwise it is written to ``<root>/etc/visland/setup-system.sh`` to run on the board
   (``sudo sh /etc/visland/setup-system.sh``), and said so.

``--dry-run`` prints all of it as the shell script that does the same and writes nothing
(docs/deploy.md shows it for ``--root /``; tests check that the script and the install make the
same files, and that the guide shows what the command prints).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from companion.packaged import MODEL_FILES, TEMPLATE, asset_path, template

__all__ = ["BOARDS", "Board", "InstallError", "add_arguments", "install", "run_from_args"]

USER = "visland"
GROUPS = ("dialout", "video")
"""The serial port's group and the camera's (V4L2 devices, /dev/video*)."""
ETC = "/etc/visland"
FLIGHTS = "/var/lib/visland/flights"
UNIT = "/etc/systemd/system/visland-companion.service"
BOOT = "/boot/firmware"
"""Raspberry Pi OS Bookworm's boot partition (``/boot`` before it)."""
SETUP_SCRIPT = f"{ETC}/setup-system.sh"


class InstallError(RuntimeError):
    """The install cannot go on (names the path and what to do)."""


@dataclass(frozen=True)
class Board:
    """A companion board: its serial port to the autopilot and the boot settings that free it.

    Attributes:
        serial: the UART device wired to the autopilot's TELEM2.
        boot_lines: lines ``config.txt`` must have (Raspberry Pi only).
        services_off: system services holding the UART, disabled.
    """

    serial: str
    boot_lines: tuple[str, ...] = ()
    services_off: tuple[str, ...] = ()


BOARDS = {
    "pi4": Board("/dev/ttyAMA0", ("enable_uart=1", "dtoverlay=disable-bt"), ("hciuart",)),
    "pi5": Board("/dev/ttyAMA0", ("dtparam=uart0",)),
    "jetson": Board("/dev/ttyTHS1"),
    "usb": Board("/dev/ttyUSB0"),
}
"""``--board``: Pi 4 (PL011 on GPIO14/15 once Bluetooth is moved off it), Pi 5 (UART0 on
GPIO14/15), a Jetson's 40-pin UART, a USB–serial adapter."""


def _unit(visland: Path, serial: str) -> str:
    device = serial.strip("/").replace("/", "-") + ".device"
    return f"""[Unit]
Description=visland companion (vision landing policy)
After=network.target {device}
Wants={device}

[Service]
Type=simple
User={USER}
Group={USER}
SupplementaryGroups={" ".join(GROUPS)}
Environment=PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
ExecStart={visland} companion --config {ETC}/companion.toml --flights 0
# SIGTERM = hand control back (LAND) and close the flight log; give it time to do so.
KillSignal=SIGTERM
TimeoutStopSec=10
Restart=on-failure
RestartSec=2
Nice=-5

[Install]
WantedBy=multi-user.target
"""


def _system_commands(board: Board) -> list[str]:
    """What only root on the board can do: the user and its groups, owners, systemd."""
    lines = [
        f"id -u {USER} >/dev/null 2>&1 || useradd --system --user-group "
        f"--home-dir /var/lib/visland --shell /usr/sbin/nologin {USER}",
        f"usermod -aG {','.join(GROUPS)} {USER}",
        f"chown -R {USER}:{USER} /var/lib/visland",
    ]
    lines += [f"systemctl disable --now {s} || true" for s in board.services_off]
    lines += ["systemctl daemon-reload", "systemctl enable visland-companion"]
    return lines


def _connect_line(board: Board) -> str:
    return f'connect = "serial:{board.serial}:921600"'


def _config_text(board: Board) -> str:
    """The template with ``connect`` set to the board's port (the dry run's ``sed``)."""
    return re.sub(
        r'^connect = "[^"]*"', _connect_line(board), template().read_text(), flags=re.MULTILINE
    )


def _under(root: Path, path: str) -> str:
    return path if root == Path("/") else str(root / path.lstrip("/"))


def dry_run_script(root: Path, board_name: str, venv: Path, *, force: bool = False) -> str:
    """The shell script that does what :func:`install` does (``--dry-run`` prints it)."""
    board = BOARDS[board_name]
    etc, boot = _under(root, ETC), _under(root, BOOT)
    assets = "$ASSETS"
    lines = [
        f"# visland companion install-service --root {root} --board {board_name} --venv {venv}"
        + (" --force" if force else ""),
        "set -eu",
        f"ASSETS=$({venv / 'bin' / 'python'} -c "
        "'import companion.packaged as p; print(p.template().parent)')",
        f"install -d -m 0755 {etc}",
        f"{'' if force else f'if [ ! -e {etc}/companion.toml ]; then '}"
        f"install -m 0644 {assets}/{TEMPLATE} {etc}/companion.toml && "
        f'sed -i \'s|^connect = "[^"]*"|{_connect_line(board)}|\' {etc}/companion.toml'
        f"{'' if force else '; fi'}",
        "install -m 0644 " + " ".join(f"{assets}/{f}" for f in MODEL_FILES) + f" {etc}/",
        f"install -d -m 0750 {_under(root, FLIGHTS)}",
        f"install -d -m 0755 {Path(_under(root, UNIT)).parent}",
        f"cat > {_under(root, UNIT)} <<'EOF'",
        _unit(venv / "bin" / "visland", board.serial).rstrip("\n"),
        "EOF",
    ]
    if board.boot_lines:
        lines.append(f"install -d -m 0755 {boot}")
    for line in board.boot_lines:
        lines.append(
            f"grep -qxF {shlex.quote(line)} {boot}/config.txt 2>/dev/null || echo "
            f"{shlex.quote(line)} >> {boot}/config.txt"
        )
    if board.boot_lines:
        lines.append(
            f"[ ! -e {boot}/cmdline.txt ] || sed -i 's/console=serial0,[0-9]* //' "
            f"{boot}/cmdline.txt"
        )
    system = _system_commands(board)
    if root == Path("/"):
        lines += system
    else:  # install writes them for the board's root to run
        script = _under(root, SETUP_SCRIPT)
        lines += [f"cat > {script} <<'EOF'", "#!/bin/sh", "set -eu", *system, "EOF"]
        lines.append(f"chmod 0755 {script}")
    return "\n".join(lines) + "\n"


def _write(path: Path, text: str, mode: int, out: TextIO) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(mode)
    print(f"wrote {path}", file=out)


def install(
    root: Path, board_name: str, venv: Path, out: TextIO, *, force: bool = False
) -> list[Path]:
    """Do the install under ``root``; returns the paths it made or kept.

    Raises:
        InstallError: a path cannot be written (names it; run as root), or the system part
            failed (names the command).
    """
    board = BOARDS[board_name]
    if not root.is_dir():
        raise InstallError(f"--root {root}: not a directory")
    visland = venv / "bin" / "visland"
    if not visland.is_file():
        raise InstallError(
            f"--venv {venv}: no {visland} (the environment visland is installed in, e.g. "
            "/opt/visland)"
        )
    etc, flights = root / ETC.lstrip("/"), root / FLIGHTS.lstrip("/")
    made: list[Path] = []
    try:
        etc.mkdir(parents=True, exist_ok=True)
        config = etc / "companion.toml"
        if config.exists() and not force:
            print(f"kept {config} (exists; --force replaces it with the template)", file=out)
        else:
            _write(config, _config_text(board), 0o644, out)
        made.append(config)
        for name in MODEL_FILES:
            shutil.copyfile(asset_path(name), etc / name)
            (etc / name).chmod(0o644)
            made.append(etc / name)
        print(f"copied the shipped model to {etc}/ ({', '.join(MODEL_FILES)})", file=out)
        flights.mkdir(parents=True, exist_ok=True)
        flights.chmod(0o750)
        made.append(flights)
        print(f"made {flights}", file=out)
        unit = root / UNIT.lstrip("/")
        _write(unit, _unit(visland, board.serial), 0o644, out)
        made.append(unit)
        made += _boot(root, board, out)
        system = _system_commands(board)
        if root == Path("/") and os.geteuid() == 0:
            for command in system:
                print(f"+ {command}", file=out)
                res = subprocess.run(["sh", "-c", command], check=False)
                if res.returncode != 0:
                    raise InstallError(f"{command!r} failed with exit {res.returncode}")
        else:
            script = root / SETUP_SCRIPT.lstrip("/")
            _write(script, "#!/bin/sh\nset -eu\n" + "\n".join(system) + "\n", 0o755, out)
            made.append(script)
            why = "not root" if os.geteuid() != 0 else f"--root {root} is not /"
            print(
                f"{why}: the user '{USER}' (groups {', '.join(GROUPS)}), the owner of "
                f"/var/lib/visland and systemd are left to {SETUP_SCRIPT}: run it on the "
                f"board as root (sudo sh {SETUP_SCRIPT})",
                file=out,
            )
    except PermissionError as exc:
        raise InstallError(
            f"{exc.filename}: permission denied; run as root (sudo), or give --root DIR"
        ) from None
    return made


def _boot(root: Path, board: Board, out: TextIO) -> list[Path]:
    """The Raspberry Pi's UART lines in config.txt, no serial console in cmdline.txt."""
    if not board.boot_lines:
        return []
    boot = root / BOOT.lstrip("/")
    config = boot / "config.txt"
    boot.mkdir(parents=True, exist_ok=True)
    text = config.read_text() if config.exists() else ""
    have = set(text.splitlines())
    missing = [line for line in board.boot_lines if line not in have]
    if missing:
        if text and not text.endswith("\n"):
            text += "\n"
        config.write_text(text + "".join(f"{line}\n" for line in missing))
    print(f"{config}: {', '.join(board.boot_lines)} (takes effect after a reboot)", file=out)
    cmdline = boot / "cmdline.txt"
    if cmdline.exists():
        words = cmdline.read_text().split()
        kept = [w for w in words if not w.startswith(("console=serial0", "console=ttyAMA0"))]
        if kept != words:
            cmdline.write_text(" ".join(kept) + "\n")
            print(f"{cmdline}: removed the serial login console", file=out)
    return [config]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--root", type=Path, default=Path("/"), help="root prefix to install under (default /)"
    )
    parser.add_argument(
        "--board",
        choices=tuple(BOARDS),
        default="pi4",
        help="pi4: /dev/ttyAMA0 with dtoverlay=disable-bt; pi5: /dev/ttyAMA0 with "
        "dtparam=uart0; jetson: /dev/ttyTHS1; usb: /dev/ttyUSB0 (default pi4)",
    )
    parser.add_argument(
        "--venv",
        type=Path,
        default=Path(sys.prefix),
        help="the environment visland is installed in: the unit's ExecStart is its "
        "bin/visland (default: this one)",
    )
    parser.add_argument(
        "--force", action="store_true", help="replace an existing /etc/visland/companion.toml"
    )
    parser.add_argument(
        "--dry-run", action="store_true", help="print the equivalent shell script, write nothing"
    )


def run_from_args(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """``visland companion install-service``: 0 done, 2 on an error (named on stderr)."""
    if args.dry_run:
        out.write(dry_run_script(args.root, args.board, args.venv, force=args.force))
        return 0
    try:
        install(args.root, args.board, args.venv, out, force=args.force)
    except (InstallError, OSError) as exc:
        print(f"visland companion install-service: error: {exc}", file=sys.stderr)
        return 2
    return 0
