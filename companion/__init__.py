"""The companion computer: contract types, MAVLink link, camera, policy runtime, safety.

Nothing here imports the rest of the project: this package must deploy alone on a small
ARM board next to a real autopilot.
"""

from companion.contract import (
    CAMERA_FOV_DEG,
    IMAGE_SIZE_PX,
    Command,
    ContractError,
    Observation,
)

__all__ = ["CAMERA_FOV_DEG", "IMAGE_SIZE_PX", "Command", "ContractError", "Observation"]
