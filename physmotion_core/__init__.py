"""PhysMotion core library: physics-grounded image-to-video, no ComfyUI imports."""

__version__ = "0.1.0"
