"""The light dome: its serial protocol, a client for it, a virtual dome on a pseudo-terminal, the
camera interface and the acquisition loop. ``docs/dome-protocol.md`` specifies the protocol."""

from .acquisition import (
    AcquisitionError,
    AcquisitionInterrupted,
    AcquisitionStopped,
    LightSettings,
    acquire,
    dome_angles,
    load_light,
    plan_directions,
)
from .camera import Camera, CameraError, CameraTimeout, FolderCamera, SimulatedCamera, SimulatedCameraConfig
from .client import (
    DomeClient,
    DomeDisconnected,
    DomeError,
    DomeFault,
    DomeIdentity,
    DomeProtocolError,
    DomeStatus,
    DomeTimeout,
)
from .emulator import DomeEmulator
from .protocol import ERROR_CODES, PROTOCOL_VERSION

__all__ = [
    "ERROR_CODES",
    "PROTOCOL_VERSION",
    "DomeClient",
    "DomeDisconnected",
    "DomeEmulator",
    "DomeError",
    "DomeFault",
    "DomeIdentity",
    "DomeProtocolError",
    "DomeStatus",
    "DomeTimeout",
    "AcquisitionError",
    "AcquisitionInterrupted",
    "AcquisitionStopped",
    "Camera",
    "CameraError",
    "CameraTimeout",
    "FolderCamera",
    "LightSettings",
    "SimulatedCamera",
    "SimulatedCameraConfig",
    "acquire",
    "dome_angles",
    "load_light",
    "plan_directions",
]
