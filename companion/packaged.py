"""What the installed package carries for a board, found through the package itself
(``importlib.resources``), never through the working directory.

``companion/assets/`` holds the hardware config template (``companion.toml``: the companion's
defaults, what ``visland companion`` loads when no ``--config`` is given) and the shipped model
beside it (``visland_vision.pt`` with its ``visland export-onnx`` graphs, and the sites
variant ``visland_vision_sites.pt`` with its own). In a source tree the
model files are links to ``models/`` (what ``visland ship`` writes); the wheel holds copies
(``pyproject.toml``, ``[tool.setuptools.package-data]``; ``make wheel``).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = [
    "MODEL_FILES",
    "TEMPLATE",
    "PackageDataError",
    "asset_path",
    "shipped_policy",
    "template",
]

TEMPLATE = "companion.toml"
"""The hardware config template's file name in ``companion/assets/``."""
MODEL_FILES = (
    "visland_vision.pt",
    "visland_vision.perception.onnx",
    "visland_vision.control.onnx",
    "visland_vision_sites.pt",
    "visland_vision_sites.perception.onnx",
    "visland_vision_sites.control.onnx",
)
"""The shipped models in ``companion/assets/``: the default model's checkpoint (first: the
config template's ``policy``), its two ONNX graphs (they stay together: the graphs carry the
checkpoint's sha256), then the variant for a pad carried by a rover or a deck
(``visland ship --name sites``; ``policy = "visland_vision_sites.pt"``) with its graphs."""


class PackageDataError(FileNotFoundError):
    """A file the package should carry is missing (a broken install or build)."""


def asset_path(name: str) -> Path:
    """The installed file ``companion/assets/<name>``.

    Raises:
        PackageDataError: not there (names the path and how to rebuild the package).
    """
    path = resources.files("companion").joinpath("assets", name)
    if not isinstance(path, Path) or not path.is_file():
        raise PackageDataError(
            f"{path}: not in the installed package (a wheel built without its package data? "
            "rebuild it with `make wheel` and reinstall)"
        )
    return path


def template() -> Path:
    """The installed hardware config template (``companion/assets/companion.toml``)."""
    return asset_path(TEMPLATE)


def shipped_policy() -> Path:
    """The installed shipped model's checkpoint (its ONNX graphs are beside it)."""
    return asset_path(MODEL_FILES[0])
