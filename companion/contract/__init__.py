"""The contract: everything that crosses a boundary between visland's parts, owned by the
companion (the part that flies on hardware) and read by every other package.

=====================  ===============================================================
module                 what it fixes
=====================  ===============================================================
``messages``           Command (thrust + FRD rates = SET_ATTITUDE_TARGET mask 128),
                       Observation (what a deployable policy sees), GroundTruth (the
                       privileged channel), ContractError, rotation_zyx (ATTITUDE's
                       Euler angles -> the FRD -> NED rotation)
``policy``             the one Policy protocol ``act(obs, groundtruth, state)`` with
                       explicit recurrent state, PolicyError, MissingGroundTruthError
``topics``             every flight-log topic name and schema name
``records``            every flight-log message's fields (frozen dataclasses, from which
                       the MCAP schema is generated), the ``/events`` kinds (EventKind);
                       ``companion_records`` the companion's, ``record_base`` the base
``camera_packet``      the UDP camera frame format (header, chunks, CRC, assembler)
``signing``            MAVLink 2 signing key parsing and PX4's unsigned allow-list
``autopilots``         the autopilot profiles (PX4, ArduPilot) as one table: mode numbers
                       (enums), parameters, arming rules; the companion's link and the
                       SITL's autopilots both read it
``perf``               LoopPerf: the wall time per part of a process's loop in flight
                       (physics, render, policy, mavlink, camera, log, wait) that the
                       SITL and the companion report and ``visland bench sitl`` reads
=====================  ===============================================================

It depends on numpy and the standard library (``signing`` and ``autopilots`` on pymavlink's
dialect, imported only by whoever needs them). Nothing here imports another visland package.
"""

from companion.contract.messages import (
    CAMERA_FOV_DEG,
    IMAGE_SIZE_PX,
    PAD_ODOMETRY_COMPONENT,
    Command,
    ContractError,
    GroundTruth,
    Observation,
    rotation_zyx,
)
from companion.contract.policy import (
    MissingGroundTruthError,
    Policy,
    PolicyError,
    PolicyState,
)

__all__ = [
    "CAMERA_FOV_DEG",
    "IMAGE_SIZE_PX",
    "PAD_ODOMETRY_COMPONENT",
    "Command",
    "ContractError",
    "GroundTruth",
    "MissingGroundTruthError",
    "Observation",
    "Policy",
    "PolicyError",
    "PolicyState",
    "rotation_zyx",
]
