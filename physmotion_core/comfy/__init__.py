"""Talking to a ComfyUI server and its workflow formats, from outside ComfyUI.

``client``: run an API-format workflow on a server over HTTP(S) and its progress websocket
(``physmotion comfy-run``, the batch's ``--comfy`` executor). ``workflow``: convert between the
API (``POST /prompt``) and UI (editor/template) formats and validate a prompt against node schemas.

Nothing here imports ComfyUI itself: this is the protocol seen from a client.
"""

from .client import ComfyCancelled, ComfyClient, ComfyError, run_workflow

__all__ = ["ComfyCancelled", "ComfyClient", "ComfyError", "run_workflow"]
