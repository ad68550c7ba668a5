"""Exceptions raised by the library.

Every error a user can trigger is one of these, with a message that names the input at fault and
what to change. They subclass ValueError/RuntimeError so callers that only know the builtins still
catch them.
"""


class PhysMotionError(Exception):
    """Base class of every error the library raises on purpose."""


class InputError(PhysMotionError, ValueError):
    """An input (image, mask, parameter, condition) is invalid. The message names it and the fix."""


class SimulationError(PhysMotionError, RuntimeError):
    """The simulation became invalid (NaN/Inf, particles leaving the domain) or cannot start."""

    def __init__(self, message: str, frame: int | None = None, material: str | None = None):
        super().__init__(message)
        self.frame = frame
        self.material = material


class MissingModelError(PhysMotionError, FileNotFoundError):
    """Weights that a learned stage needs are not in the model folders. Never downloaded."""


class Interrupted(PhysMotionError):
    """Raised by a cancel callback to stop a long loop (ComfyUI's Cancel maps onto its own exception)."""
